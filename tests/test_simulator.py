"""Tests of the simulator: determinism, ordering, and that every sensor is what it claims.

Each test checks a property a consumer relies on (the filter, the range-correction training,
the detection association, the closed-loop controller) against the simulator's ground truth.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict

import numpy as np
import pytest

from relloc.events import (
    DetectionEvent,
    GroundTruthEvent,
    OdometryEvent,
    RangeEvent,
)
from relloc.simulator import (
    Simulation,
    UwbErrorModel,
    covisibility,
    multi_scenario,
    nav_scenario,
    single_scenario,
)
from relloc.simulator.error_models import OdometryErrorModel


def _rot(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def _by_type(events, kind):
    return [e for e in events if isinstance(e, kind)]


@pytest.fixture(scope="module")
def multi() -> tuple[Simulation, list]:
    sim = multi_scenario(0, detections=True)
    return sim, list(sim.events())


# ------------------------------------------------------------------ determinism, ordering
def test_same_seed_gives_identical_events() -> None:
    a = list(multi_scenario(3, duration=8.0, detections=True).events())
    b = list(multi_scenario(3, duration=8.0, detections=True).events())
    assert a == b


def test_different_seed_gives_different_events() -> None:
    a = _by_type(multi_scenario(0, duration=5.0).events(), RangeEvent)
    b = _by_type(multi_scenario(1, duration=5.0).events(), RangeEvent)
    assert a != b


def test_events_are_time_ordered_and_within_the_run(multi) -> None:
    sim, events = multi
    t = np.array([e.t for e in events])
    assert np.all(np.diff(t) >= 0.0)
    assert t[0] >= 0.0 and t[-1] <= sim.duration
    kinds = {type(e) for e in events}
    assert kinds == {OdometryEvent, RangeEvent, DetectionEvent, GroundTruthEvent}


def test_stepwise_advance_equals_open_loop_run() -> None:
    sim = multi_scenario(2, duration=6.0, detections=True)
    stepped = []
    for t in (0.0, 0.013, 0.5, 0.5, 1.77, 3.0, 4.05, 6.0, 7.0):
        stepped += sim.advance(t)
    assert stepped == list(sim.events())


def test_sensor_streams_are_independent() -> None:
    """Switching detections on, or lengthening the run, leaves the UWB noise as it was."""
    plain = _by_type(multi_scenario(5, duration=10.0).events(), RangeEvent)
    with_det = _by_type(multi_scenario(5, duration=10.0, detections=True).events(), RangeEvent)
    longer = _by_type(multi_scenario(5, duration=20.0).events(), RangeEvent)
    assert plain == with_det
    assert plain == [e for e in longer if e.t <= 10.0]


# ------------------------------------------------------------------ team config
def test_config_is_truthful(multi) -> None:
    sim, _ = multi
    cfg = sim.config
    assert cfg.robot_names == ("r0", "r1", "r2", "r3", "r4")
    assert cfg.reference == "r0"
    assert cfg.area == (-4.0, 4.0, -4.5, 4.5)
    assert [r.uwb_node for r in cfg.robots] == ["n_0", "n_1", "n_2", "n_3", "n_4"]
    assert set(cfg.uwb.pairs) == set(sim.true_biases)
    assert len(sim.true_biases) == 10
    for key, cal in cfg.uwb.pairs.items():
        assert cal.bias == sim.true_biases[key] and cal.source == "simulator"
        assert 0.1 <= cal.bias <= 0.5
    for r in cfg.robots:
        yaw0 = sim.true_pose(r.name, 0.0)[2]
        assert math.isclose(r.heading_offset, sim.true_heading_offsets[r.name], abs_tol=1e-9)
        assert abs(math.remainder(r.heading_offset - yaw0, 2 * math.pi)) < 1e-9


def test_patterns_stay_in_the_arena_and_move_at_walking_speed(multi) -> None:
    sim, events = multi
    xmin, xmax, ymin, ymax = sim.config.area
    gt = _by_type(events, GroundTruthEvent)
    assert all(xmin < e.position[0] < xmax and ymin < e.position[1] < ymax for e in gt)
    t = np.arange(0.0, sim.duration, 0.05)
    assert np.ptp(sim.true_poses("r0", t)[:, :2], axis=0).max() == 0.0  # static reference
    for r in ("r1", "r2", "r3", "r4"):
        p = sim.true_poses(r, t)[:, :2]
        path = np.hypot(*np.diff(p, axis=0).T).sum()
        assert 0.15 * sim.duration < path < 0.3 * sim.duration  # moves 0.2-0.3 m/s, some turning
        assert 1.8 < np.ptp(p, axis=0).max() < 3.0  # 2-3 m across


# ------------------------------------------------------------------ odometry
@pytest.mark.parametrize("heading_offsets", ["start", "random"])
def test_odometry_drifts_about_one_percent_of_the_path(heading_offsets: str) -> None:
    sim = multi_scenario(1, heading_offsets=heading_offsets)
    odo = defaultdict(list)
    for e in _by_type(sim.events(), OdometryEvent):
        odo[e.robot].append((e.t, e.x, e.y))
    for robot, rows in odo.items():
        a = np.array(rows)
        truth = sim.true_poses(robot, a[:, 0])[:, :2]
        start = np.array(sim.true_pose(robot, 0.0)[:2])
        world = start + a[:, 1:] @ _rot(sim.true_heading_offsets[robot]).T
        err = np.hypot(*(world - truth).T)
        if robot == sim.config.reference:
            assert np.all(a[:, 1:] == 0.0)  # a static robot's odometry does not drift
            continue
        path = np.hypot(*np.diff(truth, axis=0).T).sum()
        assert 0.001 * path < err.max() < 0.03 * path, (robot, err.max(), path)


def test_odometry_twist_integrates_to_its_pose(multi) -> None:
    """The event's (v, w) over each interval reproduces its pose (so "twist" mode works)."""
    _, events = multi
    rows = np.array(
        [
            (e.t, e.x, e.y, e.yaw, e.v, e.w)
            for e in events
            if e.__class__ is OdometryEvent and e.robot == "r3"
        ]
    )
    x = y = yaw = 0.0
    t_prev = 0.0
    worst = 0.0
    for t, ox, oy, oyaw, v, w in rows:
        dt = t - t_prev
        chord = v * dt * np.sinc(w * dt / (2 * math.pi))
        x += chord * math.cos(yaw + 0.5 * w * dt)
        y += chord * math.sin(yaw + 0.5 * w * dt)
        yaw += w * dt
        t_prev = t
        worst = max(worst, math.hypot(x - ox, y - oy), abs(math.remainder(yaw - oyaw, 2 * math.pi)))
    assert worst < 1e-9
    assert 0.2 < np.median(rows[:, 4]) < 0.3  # r3 circles at 0.25 m/s


# ------------------------------------------------------------------ UWB
def _range_errors(sim: Simulation, events) -> dict[str, tuple[np.ndarray, np.ndarray, RangeEvent]]:
    by_pair = defaultdict(list)
    for e in _by_type(events, RangeEvent):
        by_pair[e.node_pair].append(e)
    out = {}
    for key, evs in by_pair.items():
        t = np.array([e.t for e in evs])
        pa = sim.true_poses(evs[0].robot_a, t)
        pb = sim.true_poses(evs[0].robot_b, t)
        err = np.array([e.distance for e in evs]) - np.hypot(*(pa[:, :2] - pb[:, :2]).T)
        out[key] = (t, err, evs[0])
    return out


def _robust_median(x: np.ndarray) -> float:
    m = np.median(x)
    return float(np.median(x[np.abs(x - m) < 0.25]))


def test_range_bias_per_pair_matches_true_biases() -> None:
    sim = multi_scenario(4, uwb=UwbErrorModel(orientation_amplitude=0.0))
    errors = _range_errors(sim, list(sim.events()))
    assert set(errors) == set(sim.true_biases)
    for key, (_, err, _) in errors.items():
        assert abs(_robust_median(err) - sim.true_biases[key]) < 0.01, key


def test_range_error_model_explains_bias_and_orientation(multi) -> None:
    """With the orientation term on, bias + orientation term leaves white noise + NLOS."""
    sim, events = multi
    model = sim.uwb_model
    for key, (t, err, ev) in _range_errors(sim, events).items():
        # The raw bias is still close (the orientation term is zero-mean over headings).
        assert abs(_robust_median(err) - sim.true_biases[key]) < 0.1, key
        deterministic = sim.range_error(ev.robot_a, ev.robot_b, t)
        residual = err - deterministic
        inliers = residual[residual < 0.25]
        assert abs(np.median(inliers)) < 0.01
        assert 0.8 * model.sigma < inliers.std() < 1.2 * model.sigma
        orient = deterministic - sim.true_biases[key]
        if orient.std() > 0.01:  # the heading-dependent part is really in the ranges
            assert (
                np.corrcoef(err[residual < 0.25] - sim.true_biases[key], orient[residual < 0.25])[
                    0, 1
                ]
                > 0.3
            )


def test_dropout_and_nlos_rates(multi) -> None:
    sim, events = multi
    model = sim.uwb_model
    ranges = _by_type(events, RangeEvent)
    expected = sim.duration * model.rate_hz * len(sim.true_biases)
    dropout = 1.0 - len(ranges) / expected
    assert abs(dropout - model.dropout_probability) < 0.015
    n_spikes = n = 0
    for t, err, ev in _range_errors(sim, events).values():
        residual = err - sim.range_error(ev.robot_a, ev.robot_b, t)
        n_spikes += int(np.sum(residual > 0.25))  # spikes are >= 0.3 m; noise is 0.05 m
        n += residual.size
        assert np.all(residual > -0.3)  # NLOS errors are positive only
    assert abs(n_spikes / n - model.nlos_probability) < 0.01


def test_each_pair_ranges_at_its_rate_with_its_own_phase(multi) -> None:
    _, events = multi
    stamps = defaultdict(list)
    for e in _by_type(events, RangeEvent):
        stamps[e.node_pair].append(e.t)
    phases = []
    for t in stamps.values():
        gaps = np.diff(t)
        assert abs(np.median(gaps) - 0.1) < 0.01
        phases.append(t[0] % 0.1)
    assert np.ptp(phases) > 0.02


# ------------------------------------------------------------------ detections
def test_detections_are_in_view_and_in_the_body_frame(multi) -> None:
    sim, events = multi
    cam = sim.camera
    objects = np.array([(x, y) for _, x, y in sim.objects])
    labels = [label for label, _, _ in sim.objects]
    n = 0
    for ev in _by_type(events, DetectionEvent):
        x, y, yaw = sim.true_pose(ev.robot, ev.t)
        for det in ev.objects:
            d_cam = math.hypot(det.x - cam.x, det.y - cam.y)
            bearing = math.atan2(det.y - cam.y, det.x - cam.x)
            assert d_cam < cam.max_range + 0.6
            assert abs(bearing) < math.radians(cam.fov_deg) / 2 + 0.05
            world = np.array([x, y]) + _rot(yaw) @ np.array([det.x, det.y])
            dist = np.hypot(*(objects - world).T)
            j = int(np.argmin(dist))
            assert labels[j] == det.label
            assert dist[j] < 5 * (0.02 + 0.02 * d_cam) + 0.05 * d_cam
            n += 1
    assert n > 500


def test_misses_and_covisibility(multi) -> None:
    sim, events = multi
    frames = _by_type(events, DetectionEvent)
    assert len(frames) == pytest.approx(5 * 5.0 * sim.duration, rel=0.01)
    cov = covisibility(sim)
    assert cov["any"] > 0.6  # some pair sees a common object most of the time
    assert sum(v > 0.1 for k, v in cov.items() if k.startswith("r")) >= 5
    assert cov["r0-r1"] > 0.1 or cov["r0-r2"] > 0.1  # the reference takes part too


def test_no_detections_unless_asked() -> None:
    sim = multi_scenario(0, duration=5.0)
    assert sim.objects == []
    assert not _by_type(sim.events(), DetectionEvent)


# ------------------------------------------------------------------ closed loop
def test_commanding_moves_the_robot() -> None:
    sim = nav_scenario(0, duration=20.0)
    assert sim.commanded == ("r2",)
    start = sim.true_pose("r2", 0.0)
    sim.advance(1.0)
    assert sim.true_pose("r2", 1.0) == pytest.approx(start)  # no command: stands still
    sim.set_command("r2", 0.2, 0.0)
    events = sim.advance(6.0)
    x, y, yaw = sim.true_pose("r2", 6.0)
    moved = np.array([x - start[0], y - start[1]])
    heading = np.array([math.cos(start[2]), math.sin(start[2])])
    assert moved @ heading == pytest.approx(1.0, rel=0.05)
    assert abs(moved @ np.array([-heading[1], heading[0]])) < 0.1
    sim.set_command("r2", 0.0, 0.5)
    events += sim.advance(8.0)
    assert math.remainder(sim.true_pose("r2", 8.0)[2] - yaw, 2 * math.pi) == pytest.approx(
        1.0, abs=0.1
    )
    odo = [e for e in _by_type(events, OdometryEvent) if e.robot == "r2"]
    assert math.hypot(odo[-1].x, odo[-1].y) == pytest.approx(1.0, rel=0.06)
    with pytest.raises(ValueError):
        sim.true_pose("r2", 15.0)  # not simulated yet
    with pytest.raises(ValueError):
        sim.set_command("r1", 0.1, 0.0)  # follows its pattern


def test_commanded_robot_leaves_the_others_unchanged() -> None:
    nav = nav_scenario(0, duration=5.0)
    nav.set_command("r2", 0.3, 0.2)
    stepped = nav.advance(5.0)
    plain = list(multi_scenario(0, duration=5.0).events())
    for kind in (GroundTruthEvent, OdometryEvent):
        assert [e for e in stepped if isinstance(e, kind) and e.robot != "r2"] == [
            e for e in plain if isinstance(e, kind) and e.robot != "r2"
        ]


# ------------------------------------------------------------------ single, options, speed
def test_single_scenario_is_one_pair_and_circles() -> None:
    sim = single_scenario(0)
    assert sim.config.robot_names == ("r0", "r1") and sim.config.reference == "r0"
    assert list(sim.true_biases) == ["n_0-n_1"]
    t = np.arange(0.0, sim.duration, 0.05)
    p = sim.true_poses("r1", t)[:, :2]
    assert 9.0 < np.hypot(*np.diff(p, axis=0).T).sum() < 11.0
    assert np.ptp(p, axis=0) == pytest.approx([2.0, 2.0], abs=0.05)  # 1 m radius
    ranges = _by_type(sim.events(), RangeEvent)
    assert len(ranges) / sim.duration == pytest.approx(9.5, abs=0.5)


def test_random_heading_offsets_are_random_and_exposed() -> None:
    a = multi_scenario(0, heading_offsets="random")
    b = multi_scenario(1, heading_offsets="random")
    assert a.true_heading_offsets != b.true_heading_offsets
    for r in a.robots:
        assert a.config.robot(r).heading_offset == pytest.approx(a.true_pose(r, 0.0)[2])
    with pytest.raises(ValueError):
        multi_scenario(0, heading_offsets="north")  # type: ignore[arg-type]


def test_generating_the_multi_run_is_fast() -> None:
    # CPU time: a loaded machine stretches the wall clock, not the work done
    start = time.process_time()
    sim = multi_scenario(0, detections=True)
    n = sum(1 for _ in sim.events())
    elapsed = time.process_time() - start
    assert n > 15000
    assert elapsed < 1.5  # typically about 0.1 s


def test_a_wheel_scale_step_lengthens_the_odometry_from_its_time_on() -> None:
    """Without odometry noise, the odometry's path length over the true one is the drawn wheel
    scale before the step and that scale times the factor after it."""
    quiet = OdometryErrorModel(sigma_v=0.0, sigma_w=0.0, gyro_bias_max=0.0)
    stepped = OdometryErrorModel(
        sigma_v=0.0, sigma_w=0.0, gyro_bias_max=0.0, scale_step=(20.0, 1.2)
    )
    lengths = {}
    for name, model in (("quiet", quiet), ("stepped", stepped)):
        sim = multi_scenario(seed=0, duration=40.0, odometry=model)
        odom = [e for e in _by_type(sim.events(), OdometryEvent) if e.robot == "r1"]
        xy = np.array([(e.x, e.y) for e in odom])
        t = np.array([e.t for e in odom])
        steps = np.hypot(*np.diff(xy, axis=0).T)
        lengths[name] = (steps[t[1:] <= 20.0].sum(), steps[t[1:] > 20.0].sum())
    assert lengths["stepped"][0] == pytest.approx(lengths["quiet"][0])
    assert lengths["stepped"][1] == pytest.approx(1.2 * lengths["quiet"][1], rel=1e-3)
