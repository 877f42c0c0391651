"""The flying team's simulation (``drones``, ``drones_uwb``): a 3D config with two tags at 3D
lever arms per drone, 3D ground truth, ranges between tags in 3D, velocity odometry in each
drone's own frame, heights, and seeded, repeatable events."""

from __future__ import annotations

import math
from collections import defaultdict
from itertools import combinations
from typing import TypeVar

import numpy as np
import pytest

from relloc import geometry
from relloc.events import (
    Event,
    GroundTruthEvent,
    HeightEvent,
    OdometryEvent,
    RangeEvent,
    pair_key,
)
from relloc.simulator.flight import (
    DRONE_UWB,
    HEIGHT_SENSOR,
    SIX_TAG_ARMS,
    SIX_TAG_UWB,
    FlightSimulation,
    drones_scenario,
    drones_six_scenario,
    drones_uwb_scenario,
)
from relloc.simulator.scenarios import SCENARIOS

E = TypeVar("E")

DURATION = 30.0
DRONES = ("d0", "d1", "d2", "d3", "d4")


@pytest.fixture(scope="module")
def sim() -> FlightSimulation:
    return drones_scenario(0, duration=DURATION)


@pytest.fixture(scope="module")
def events(sim: FlightSimulation) -> list[Event]:
    return list(sim.events())


def _of(events: list[Event], kind: type[E]) -> list[E]:
    return [e for e in events if isinstance(e, kind)]


def test_the_scenarios_are_registered_and_the_config_is_3d_with_two_tags_a_drone(
    sim: FlightSimulation,
) -> None:
    assert SCENARIOS["drones"] is drones_scenario and SCENARIOS["drones_uwb"] is drones_uwb_scenario
    config = sim.config
    assert config.dimension == 3 and config.reference == "d0"
    assert config.robot_names == DRONES
    for i, rc in enumerate(config.robots):
        assert rc.nodes == (f"n_{i}a", f"n_{i}b") and rc.odom_topic
        arms = [t.lever_arm for t in rc.tags]
        assert all(len(a) == 3 for a in arms)
        assert math.dist(*arms) == pytest.approx(0.3)
    xmin, xmax, ymin, ymax = config.area
    for robot in DRONES:
        p = sim.true_positions(robot, np.linspace(0.0, 60.0, 601))
        assert (p[:, 0] > xmin).all() and (p[:, 0] < xmax).all()
        assert (p[:, 1] > ymin).all() and (p[:, 1] < ymax).all()
        assert (p[:, 2] > 0.75).all() and (p[:, 2] < 3.0).all()
    tags = [(r.name, t.node) for r in config.robots for t in r.tags]
    assert set(sim.true_biases) == {
        pair_key(na, nb) for (ra, na), (rb, nb) in combinations(tags, 2) if ra != rb
    }
    assert all(0.1 <= b <= 0.5 for b in sim.true_biases.values())


def test_ground_truth_is_3d_at_heights_that_differ_and_vary_at_most_1_m_s(
    events: list[Event],
) -> None:
    track: dict[str, list[GroundTruthEvent]] = defaultdict(list)
    for e in _of(events, GroundTruthEvent):
        track[e.robot].append(e)
    assert set(track) == set(DRONES)
    heights = {}
    for robot, gts in track.items():
        p = np.array([g.position for g in gts])
        assert p.shape[1] == 3
        assert np.ptp(p[:, 2]) > 0.2  # a slow vertical oscillation
        heights[robot] = float(p[:, 2].mean())
        speed = np.hypot(*np.diff(p[:, :2], axis=0).T) / 0.05
        assert speed.max() < 1.0
        yaw = np.unwrap([g.yaw for g in gts])
        assert np.ptp(yaw) > 0.3
    means = sorted(heights.values())
    assert means[-1] - means[0] > 0.5
    assert min(np.diff(means)) > 0.2  # every drone at its own height


def test_every_range_is_the_3d_tag_distance_plus_the_pair_bias(
    sim: FlightSimulation, events: list[Event]
) -> None:
    ranges = _of(events, RangeEvent)
    assert len({e.node_pair for e in ranges}) == 40  # 10 drone pairs, 4 tag pairs each
    assert all(e.robot_a != e.robot_b for e in ranges)
    # ten pairs a second, 5 % dropped
    assert len(ranges) == pytest.approx(40 * 10 * DURATION * 0.95, rel=0.03)
    residual = []
    flat = []
    for robot_a, robot_b, node_a, node_b in {
        (e.robot_a, e.robot_b, e.node_a, e.node_b) for e in ranges
    }:
        mine = [e for e in ranges if e.node_a == node_a and e.node_b == node_b]
        tt = np.array([e.t for e in mine])
        ends = []
        for robot, node in ((robot_a, node_a), (robot_b, node_b)):
            p = sim.true_positions(robot, tt)
            yaw = sim.true_poses(robot, tt)[:, 2]
            ends.append(geometry.tag_position(p, yaw, sim.config.lever_arm(node)))
        dist = np.linalg.norm(ends[0] - ends[1], axis=1)
        flat_dist = np.linalg.norm(ends[0][:, :2] - ends[1][:, :2], axis=1)
        measured = np.array([e.distance for e in mine]) - sim.true_biases[mine[0].node_pair]
        residual.append(measured - dist)
        flat.append(measured - flat_dist)
    res = np.concatenate(residual)
    assert res.size == len(ranges)
    # white noise, and a few NLOS spikes (positive, up to nlos_range's top)
    spikes = res > 4.5 * DRONE_UWB.sigma
    assert spikes.mean() == pytest.approx(DRONE_UWB.nlos_probability, abs=0.01)
    assert res.min() > -4.5 * DRONE_UWB.sigma and res.max() < DRONE_UWB.nlos_range[1] + 0.3
    white = res[~spikes]
    assert abs(white.mean()) < 0.005 and white.std() == pytest.approx(DRONE_UWB.sigma, rel=0.1)
    # the heights matter: the horizontal distance would be well off
    assert np.abs(np.concatenate(flat)).mean() > 2 * DRONE_UWB.sigma


def test_odometry_integrated_back_follows_the_motion_in_the_drones_own_frame(
    sim: FlightSimulation, events: list[Event]
) -> None:
    odometry = _of(events, OdometryEvent)
    for robot in DRONES:
        odo = [e for e in odometry if e.robot == robot]
        assert len(odo) == pytest.approx(20 * DURATION, abs=1)
        t = np.array([e.t for e in odo])
        xyz = np.array([(e.x, e.y, e.z) for e in odo])
        yaw = np.unwrap([e.yaw for e in odo])
        true_p = sim.true_positions(robot, t)
        true_yaw = np.unwrap(sim.true_poses(robot, t)[:, 2])
        # the frame: the start pose (its own yaw offset, not the world's)
        offset = sim.true_heading_offsets[robot]
        assert math.degrees(offset) == pytest.approx(sim.config.robot(robot).heading_offset_deg)
        assert np.abs(xyz[0]).max() < 0.06 and abs(yaw[0]) < 0.01
        c, s = math.cos(offset), math.sin(offset)
        d = true_p - true_p[0]
        in_frame = np.column_stack([c * d[:, 0] + s * d[:, 1], c * d[:, 1] - s * d[:, 0], d[:, 2]])
        drift = np.linalg.norm(xyz[:, :2] - in_frame[:, :2], axis=1)
        travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(d, axis=0), axis=1))])
        assert (drift < 0.1 + 0.05 * travelled).all()
        assert np.abs(xyz[:, 2] - in_frame[:, 2]).max() < 0.05
        # the heading drifts with the drone's gyro bias, and a little noise
        yaw_drift = (yaw - yaw[0]) - (true_yaw - true_yaw[0])
        assert abs(sim.true_gyro_biases[robot]) <= sim.flight_odometry.gyro_bias_max
        assert np.abs(yaw_drift - sim.true_gyro_biases[robot] * (t - t[0])).max() < 0.05
        # 5 s windows, in the body frame at the window's start: displacement within 10 %
        for k in range(0, len(t) - 100, 50):
            mine = np.subtract(xyz[k + 100], xyz[k])[:2]
            true = np.subtract(true_p[k + 100], true_p[k])[:2]
            body = _turn(mine, -yaw[k])
            true_body = _turn(true, -true_yaw[k])
            assert np.linalg.norm(body - true_body) <= 0.1 * np.linalg.norm(true_body) + 0.02
        # the reported twist: the forward speed and the yaw rate
        v = np.array([e.v for e in odo])
        assert np.abs(v).max() < 1.0 and np.ptp(v) > 0.2


def _turn(v: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def test_heights_are_within_four_sigma_at_10_hz(sim: FlightSimulation, events: list[Event]) -> None:
    heights = _of(events, HeightEvent)
    for robot in DRONES:
        mine = [e for e in heights if e.robot == robot]
        assert len(mine) == pytest.approx(10 * DURATION, abs=1)
        t = np.array([e.t for e in mine])
        err = np.array([e.z for e in mine]) - sim.true_positions(robot, t)[:, 2]
        assert all(e.sigma == HEIGHT_SENSOR.sigma for e in mine)
        assert np.abs(err).max() < 4 * HEIGHT_SENSOR.sigma
        assert err.std() == pytest.approx(HEIGHT_SENSOR.sigma, rel=0.2)


def test_drones_uwb_flies_the_same_with_ranges_only(
    sim: FlightSimulation, events: list[Event]
) -> None:
    uwb = drones_uwb_scenario(0, duration=DURATION)
    assert not any(r.odom_topic for r in uwb.config.robots) and uwb.config.dimension == 3
    others = list(uwb.events())
    assert not _of(others, OdometryEvent) and not _of(others, HeightEvent)
    assert _of(others, GroundTruthEvent) == _of(events, GroundTruthEvent)
    assert _of(others, RangeEvent) == _of(events, RangeEvent)
    assert uwb.true_biases == sim.true_biases


def test_the_same_seed_gives_the_same_events_however_the_run_is_stepped(
    events: list[Event],
) -> None:
    again = drones_scenario(0, duration=DURATION)
    assert list(again.events()) == events
    stepped: list[Event] = []
    for t in np.arange(0.7, DURATION + 0.7, 0.7):
        stepped += again.advance(float(t))
    assert sorted(map(repr, stepped)) == sorted(map(repr, events))
    other = drones_scenario(1, duration=DURATION)
    assert _of(list(other.events()), GroundTruthEvent) != _of(events, GroundTruthEvent)


def test_random_heading_offsets_turn_the_odometry_frames() -> None:
    start = drones_scenario(0, duration=5.0)
    turned = drones_scenario(0, duration=5.0, heading_offsets="random")
    assert start.true_heading_offsets != turned.true_heading_offsets
    for robot in DRONES:
        assert turned.config.robot(robot).heading_offset_deg == pytest.approx(
            math.degrees(turned.true_heading_offsets[robot])
        )
    with pytest.raises(ValueError, match="heading_offsets"):
        drones_scenario(0, heading_offsets="north")  # type: ignore[arg-type]


def test_drones_six_ranges_every_tag_pair_at_1_hz_averaged_over_the_past_second() -> None:
    """Three drones, six tags each, no odometry nor heights; each range the mean distance over
    the second before its stamp (not the distance at the stamp) plus the bias and noise."""
    sim = drones_six_scenario(0, duration=10.0)
    assert SCENARIOS["drones_six"] is drones_six_scenario
    config = sim.config
    assert config.robot_names == ("d0", "d1", "d2") and config.dimension == 3
    assert all(len(r.tags) == 6 and not r.odom_topic and not r.height_topic for r in config.robots)
    events = list(sim.events())
    assert not _of(events, OdometryEvent) and not _of(events, HeightEvent)
    ranges = _of(events, RangeEvent)
    assert len({e.node_pair for e in ranges}) == 3 * 36
    assert len(ranges) == pytest.approx(3 * 36 * 10 * 0.95, rel=0.05)
    averaged, instant = [], []
    for e in ranges:
        if e.t < 1.0:
            continue
        tt = np.linspace(e.t - 1.0, e.t, 41)
        ends = []
        for robot, node in ((e.robot_a, e.node_a), (e.robot_b, e.node_b)):
            p = sim.true_positions(robot, tt)
            yaw = sim.true_poses(robot, tt)[:, 2]
            ends.append(geometry.tag_position(p, yaw, sim.config.lever_arm(node)))
        dist = np.linalg.norm(ends[0] - ends[1], axis=1)
        measured = e.distance - sim.true_biases[e.node_pair]
        averaged.append(measured - dist.mean())
        instant.append(measured - dist[-1])
    assert np.std(averaged) == pytest.approx(SIX_TAG_UWB.sigma, rel=0.15)
    assert np.std(instant) > 2.0 * SIX_TAG_UWB.sigma
    assert max(math.dist(a, b) for a in SIX_TAG_ARMS for b in SIX_TAG_ARMS) <= 0.5
