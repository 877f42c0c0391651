"""The 3D smoother (``kind = "smoother3d"``): its factors, its covariance and a simulated flight."""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
import pytest

from relloc.config import ConfigError
from relloc.estimators import registry
from relloc.estimators.smoother3d.graph import (
    Motion,
    PoseWindow,
    TagRanges,
    _constant_velocity,
    _height,
    _tag_range,
    pose_of,
)
from relloc.estimators.smoother3d.localizer import PoseSmootherLocalizer
from relloc.estimators.smoother3d.start import level_start
from relloc.events import GroundTruthEvent, HeightEvent
from relloc.methods import MethodError, build_pipeline
from relloc.simulator.flight import drones_scenario, drones_six_scenario, drones_uwb_scenario


def _numeric_jacobian(error, values: gtsam.Values, keys: list[int], k: int) -> np.ndarray:
    """d error / d (right perturbation of pose key ``keys[k]``), by central differences."""
    eps = 1e-6
    columns = []
    for j in range(6):
        d = np.zeros(6)
        d[j] = eps
        rows = []
        for sign in (1.0, -1.0):
            shifted = gtsam.Values(values)
            shifted.update(keys[k], values.atPose3(keys[k]).retract(sign * d))
            rows.append(np.asarray(error(_Factor(keys), shifted, None)))
        columns.append((rows[0] - rows[1]) / (2 * eps))
    return np.stack(columns, axis=1)


class _Factor:
    def __init__(self, keys: list[int]) -> None:
        self._keys = keys

    def keys(self) -> list[int]:
        return self._keys


def test_the_tag_range_and_height_jacobians_are_the_numeric_ones() -> None:
    values = gtsam.Values()
    keys = [gtsam.symbol("x", 0), gtsam.symbol("x", 1), gtsam.symbol("b", 0)]
    values.insert(keys[0], pose_of(np.array([0.3, -0.2, 1.1, 0.7])))
    values.insert(keys[1], pose_of(np.array([2.0, 1.5, 2.4, -2.1])))
    values.insert(keys[2], np.array([0.25]))
    arm_a, arm_b = np.array([0.15, 0.02, 0.05]), np.array([-0.15, 0.0, 0.05])
    error = _tag_range(3.0, arm_a, arm_b)
    jac: list[np.ndarray] = [np.zeros((1, 6)), np.zeros((1, 6)), np.zeros((1, 1))]
    value = error(_Factor(keys), values, jac)
    ta = values.atPose3(keys[0]).transformFrom(arm_a)
    tb = values.atPose3(keys[1]).transformFrom(arm_b)
    assert value[0] == pytest.approx(np.linalg.norm(ta - tb) + 0.25 - 3.0)
    for k in (0, 1):
        assert jac[k] == pytest.approx(_numeric_jacobian(error, values, keys, k), abs=1e-6)
    assert jac[2][0, 0] == 1.0
    height = _height(1.0)
    hj: list[np.ndarray] = [np.zeros((1, 6))]
    assert height(_Factor(keys[:1]), values, hj)[0] == pytest.approx(0.1)
    assert hj[0] == pytest.approx(_numeric_jacobian(height, values, keys[:1], 0), abs=1e-6)


def test_the_constant_velocity_jacobians_are_the_numeric_ones() -> None:
    """Three keys of a robot without odometry: the change of mean velocity and yaw rate."""
    values = gtsam.Values()
    keys = [gtsam.symbol("x", k) for k in range(3)]
    rows = ([0.0, 0.0, 1.0, 3.1], [0.2, 0.1, 1.1, -3.1], [0.5, 0.1, 1.0, -2.9])
    for key, row in zip(keys, rows, strict=True):
        values.insert(key, pose_of(np.array(row)))
    error = _constant_velocity(0.1, 0.2)
    jac: list[np.ndarray] = [np.zeros((4, 6)) for _ in keys]
    value = error(_Factor(keys), values, jac)
    v1 = (np.array(rows[1][:3]) - rows[0][:3]) / 0.1
    v2 = (np.array(rows[2][:3]) - rows[1][:3]) / 0.2
    turn1 = math.remainder(-3.1 - 3.1, math.tau) / 0.1  # across +-pi: a small turn
    assert value[:3] == pytest.approx(v2 - v1)
    assert value[3] == pytest.approx(0.2 / 0.2 - turn1)
    for k in range(3):
        assert jac[k] == pytest.approx(_numeric_jacobian(error, values, keys, k), abs=1e-5)


def test_only_robots_without_any_odometry_get_the_constant_velocity() -> None:
    """A robot with odometry whose yaw is still sought walks like a blind one, but only the
    blind robot's keys are tied by a constant velocity (one factor a step from the third)."""
    none = np.zeros(0, np.intp)
    ranges = TagRanges(none, none, none, none, np.zeros((0, 3)), np.zeros((0, 3)),
                       np.zeros(0), np.zeros(0), none)  # fmt: skip
    window = PoseWindow(3, 0, 10.0, None, blind=np.array([False, False, True]))
    poses = np.array([[0.0, 0.0, 1.0, 0.0], [2.0, 0.0, 1.0, 0.0], [0.0, 2.0, 1.5, 0.0]])
    window.start(0.0, poses, np.full((3, 4), 0.1), ranges=ranges, heights={})
    walk = Motion(np.zeros((3, 4)), np.full((3, 4), 0.1), np.zeros(3, bool), 0.1)
    for k in range(1, 5):
        window.advance(0.1 * k, walk, ranges=ranges, heights={})
    graph = window.smoother.getFactors()
    velocity = [graph.at(i) for i in range(graph.size()) if graph.at(i) and graph.at(i).dim() == 4]
    blind_keys = {gtsam.symbol("x", s * 3 + 2) for s in range(5)}
    assert len(velocity) == 3  # steps 2, 3 and 4
    assert all(set(f.keys()) <= blind_keys for f in velocity)


def test_the_level_start_places_a_flying_team_and_its_mirror_image() -> None:
    """Three robots, two tags each, exact ranges and heights: the first hypothesis or its
    mirror image is the truth in the reference's frame."""
    truth = np.array([[0.0, 0.0, 1.0, 0.0], [3.0, 1.0, 2.0, 1.0], [-1.0, 2.5, 1.5, -2.0]])
    arms = np.array([[0.15, 0.0, 0.05], [-0.15, 0.0, 0.05]] * 3)
    tag_robot = np.repeat(np.arange(3), 2)
    tags = np.array(
        [pose_of(truth[r]).transformFrom(a) for r, a in zip(tag_robot, arms, strict=True)]
    )
    ta, tb = np.array([(i, j) for i in range(6) for j in range(i + 1, 6) if i // 2 != j // 2]).T
    d = np.linalg.norm(tags[ta] - tags[tb], axis=1)
    started = level_start(tag_robot, arms, truth[:, 2].copy(), (ta, tb, d), 0, np.full(3, 0.1))
    assert started is not None
    poses, sigma, rms = started
    assert poses.shape == (2, 3, 4) and rms < 1e-3
    best = min(np.abs(poses[m] - truth).max() for m in range(2))
    assert best < 1e-3
    assert np.all(sigma[..., 3] < 1.0)  # two tags each: every yaw placed


def test_auto_flies_the_drones_and_the_planar_kinds_refuse_them() -> None:
    config = drones_scenario(0, duration=5.0).config
    kind, why = registry.choose(config)
    assert kind.name == "smoother3d" and "dimension = 3" in why
    with pytest.raises(ConfigError, match="cannot estimate in 3D"):
        registry.check(config.with_filter(kind="smoother"))
    with pytest.raises(MethodError, match="2D only"):
        build_pipeline("multilateration", config)


def _run(sim_factory, seed: int, duration: float, keeps_run: bool = True):
    """The scenario's run with online biases and no calibration (as ``relloc demo --bias
    online`` runs it)."""
    sim = sim_factory(seed, duration=duration)
    uncalibrated = dataclasses.replace(sim.config.uwb, pairs={})
    config = dataclasses.replace(sim.config, uwb=uncalibrated).with_modes(bias="online")
    loc = PoseSmootherLocalizer(config, seed=seed)
    loc.keeps_run = keeps_run
    truth: dict[str, list[tuple[float, np.ndarray, float]]] = {}
    estimates = []
    for ev in sim.events():
        if isinstance(ev, GroundTruthEvent):
            truth.setdefault(ev.robot, []).append((ev.t, np.array(ev.position), ev.yaw))
        else:
            estimates += loc.process(ev)
    return sim, loc, estimates + loc.flush(), truth


def _body_errors(estimates, truth, reference: str, after: float):
    """Per robot: 3D position errors in the reference's level body frame, yaw errors (rad),
    and whether the 95 % ellipsoid held the truth."""
    times = {r: np.array([s[0] for s in rows]) for r, rows in truth.items()}

    def at(robot: str, t: float) -> tuple[np.ndarray, float]:
        k = int(np.argmin(np.abs(times[robot] - t)))
        return truth[robot][k][1], truth[robot][k][2]

    out: dict[str, tuple[list[float], list[float], list[bool]]] = {}
    for est in estimates:
        if est.t < after:
            continue
        pr, yr = at(reference, est.t)
        c, s = math.cos(yr), math.sin(yr)
        for robot, p in est.positions.items():
            pt, yt = at(robot, est.t)
            d = pt - pr
            body = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])
            e = np.array(p) - body
            yaw = math.remainder(est.yaws[robot][0] - (yt - yr), math.tau)
            nees = float(e @ np.linalg.solve(np.array(est.covariances[robot]), e))
            row = out.setdefault(robot, ([], [], []))
            row[0].append(float(np.linalg.norm(e)))
            row[1].append(abs(yaw))
            row[2].append(nees < 7.815)
    return out


def test_a_flying_team_with_odometry_and_heights_is_placed_in_the_references_body_frame() -> None:
    sim, loc, estimates, truth = _run(drones_scenario, 0, 40.0)
    assert loc.stats["smoother_yaws_from_motion_rms_mm"] > 0  # two close tags: yaws from motion
    assert estimates[-1].frame == "body" and estimates[-1].dimension == 3
    assert estimates[-1].orientation_observable
    errors = _body_errors(estimates, truth, sim.config.reference, 15.0)
    assert set(errors) == {"d1", "d2", "d3", "d4"}
    for robot, (ape, yaw, covered) in errors.items():
        assert np.median(ape) < 0.08, robot
        assert math.degrees(float(np.median(yaw))) < 3.0, robot
        assert np.mean(covered) > 0.85, robot
    biases = estimates[-1].biases
    err = [abs(biases[k][0] - b) for k, b in sim.true_biases.items()]
    assert np.median(err) < 0.04


def test_heights_are_validated_and_counted() -> None:
    loc = PoseSmootherLocalizer(drones_scenario(0, duration=5.0).config)
    loc.process(HeightEvent(1.0, "d1", 1.5, 0.04))
    loc.process(HeightEvent(1.0, "ghost", 1.5))
    loc.process(HeightEvent(1.0, "d1", math.nan))
    loc.process(HeightEvent(1.0, "d1", 1.0, 0.0))
    assert loc.stats["height"] == 1
    assert loc.rejected == {"unknown_robot": 1, "invalid_height": 2}


def test_a_served_run_keeps_nothing_to_smooth() -> None:
    """A live server's localizer (``keeps_run`` off) publishes as before and holds no
    smoothed run: its memory stays bounded."""
    _, loc, estimates, _ = _run(drones_uwb_scenario, 0, 8.0, keeps_run=False)
    assert estimates and loc.smoothed_estimates() == [] and not loc._unsmoothed


def test_ranges_alone_leave_the_orientation_unobservable() -> None:
    """Two tags a drone and no odometry: ranges never tell the formation from its mirror
    image, and the estimate says so."""
    _, _, estimates, _ = _run(drones_uwb_scenario, 0, 20.0)
    assert estimates and not any(e.orientation_observable for e in estimates)


def test_six_tags_a_drone_without_odometry_tell_the_orientation() -> None:
    """``drones_six`` (1 Hz averaged ranges, no odometry, online biases), 30 s of seed 0: the
    reference's six tags make the orientation observable. Ranges placed half their window
    before their stamps (the config's ``uwb.range_delay``), hypotheses kept 15 s (the
    least-cost one published) and a constant velocity between keys, vertically a tenth of the
    horizontal: 0.25 / 0.23 m and 2.8 / 3.1 deg median (isotropic: 0.26 / 0.25 m and 2.9 / 2.7
    deg; the first hypothesis published: 0.35 / 0.29 m; a random walk alone: 0.42 / 0.35 m and
    4.6 / 3.6 deg; docs/explanation/flying.md); smoothed 5 s later, 0.15 / 0.19 m and 1.6 /
    2.8 deg."""
    sim, loc, estimates, truth = _run(drones_six_scenario, 0, 30.0)
    assert sim.config.uwb.range_delay == 0.5
    assert estimates[-1].orientation_observable
    errors = _body_errors(estimates, truth, sim.config.reference, 10.0)
    assert set(errors) == {"d1", "d2"}
    for robot, (ape, yaw, _) in errors.items():
        assert np.median(ape) < 0.4, robot
        assert math.degrees(float(np.median(yaw))) < 4.0, robot
    # while several hypotheses are kept, the one the ranges fit best is published (the first
    # one made, as before: 1-5 m off until the others were dropped at 15 s)
    undecided = [e for e in estimates if e.n_modes > 1 and e.t >= 5.0]
    assert undecided and not undecided[-1].orientation_observable
    early = _body_errors(undecided, truth, sim.config.reference, 5.0)
    for robot, (ape, _, _) in early.items():
        assert np.median(ape) < 0.6, robot
    # the run smoothed at a fixed lag: each step as the window saw it SMOOTH_DELAY later
    smoothed = loc.smoothed_estimates()
    assert [e.t for e in smoothed] == [e.t for e in estimates]
    better = _body_errors(smoothed, truth, sim.config.reference, 10.0)
    for robot, (ape, yaw, covered) in better.items():
        assert np.median(ape) < 0.8 * np.median(errors[robot][0]), robot
        assert np.median(yaw) < np.median(errors[robot][1]), robot
        assert np.mean(covered) > 0.9, robot
