"""The detection-association stage: which detections of two robots are the same object.

Hand-built scenes check the decisions one by one (two objects in view and a decoy, gates,
ambiguity, invalid depth, motion between captures); a simulated run checks that nothing wrong
gets through on realistic data, and a short filter run that the observations are fused.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from relloc.config import AssociationConfig, PairCalibration, RobotConfig, TeamConfig, UwbConfig
from relloc.engine import Engine
from relloc.estimate import Estimate
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.events import (
    DetectionEvent,
    Event,
    GroundTruthEvent,
    ObjectDetection,
    OdometryEvent,
    RangeEvent,
    RelativeObservation,
)
from relloc.methods import build_pipeline
from relloc.simulator import multi_scenario, single_scenario
from relloc.stages.association import REJECTIONS, DetectionAssociator

BIAS = 0.25
"""UWB bias of the n_0-n_1 pair in the hand-built team."""


def _team(**association: float) -> TeamConfig:
    robots = (RobotConfig("r0", uwb_node="n_0"), RobotConfig("r1", uwb_node="n_1"))
    uwb = UwbConfig(pairs={"n_0-n_1": PairCalibration(bias=BIAS)})
    return TeamConfig(robots, reference="r0", uwb=uwb, association=AssociationConfig(**association))


# The scene: r0 at the origin facing +x, r1 at (4, 0) facing r0 (heading pi). The odometry
# frames are the world frame (heading offsets 0), so the true answer is p_r1 - p_r0 = (4, 0).
R1 = (4.0, 0.0)
CHAIR_A = (2.0, 1.0)
BOTTLE_B = (2.0, -1.0)
# A second chair that r1 does not see, placed so that pairing it with r1's view of chair A
# implies a vector as long as the UWB range: only consistency can tell it from the true pair.
CHAIR_C = (-2.0 + 4.0 * math.cos(math.radians(30)), 1.0 + 4.0 * math.sin(math.radians(30)))


def _body(
    robot_xy: tuple[float, float], yaw: float, world: tuple[float, float]
) -> tuple[float, float]:
    """A world point in the body frame of a robot at ``robot_xy`` with heading ``yaw``."""
    dx, dy = world[0] - robot_xy[0], world[1] - robot_xy[1]
    c, s = math.cos(yaw), math.sin(yaw)
    return c * dx + s * dy, -s * dx + c * dy


def _seen(robot: str, t: float, *objects: tuple[str, tuple[float, float]]) -> DetectionEvent:
    pose = ((0.0, 0.0), 0.0) if robot == "r0" else (R1, math.pi)
    dets = tuple(ObjectDetection(label, *_body(*pose, xy)) for label, xy in objects)
    return DetectionEvent(t, robot, dets)


def _setup(stage: DetectionAssociator, *, with_range: bool = True) -> None:
    """Both robots' odometry (standing still) and, optionally, a UWB range at t = 1."""
    for t in (0.0, 0.5, 1.0, 1.5):
        stage.process(OdometryEvent(t, "r0", 0.0, 0.0, 0.0))
        stage.process(OdometryEvent(t, "r1", *R1, math.pi))
    if with_range:
        stage.process(RangeEvent(1.0, "r0", "r1", 4.0 + BIAS, "n_0", "n_1"))


def _observations(events: list[Event]) -> list[RelativeObservation]:
    return [e for e in events if isinstance(e, RelativeObservation)]


def _r1_minus_r0(o: RelativeObservation) -> tuple[float, float]:
    """The measured ``p_r1 - p_r0`` whichever robot the observation names as observer."""
    sign = 1.0 if (o.observer, o.target) == ("r0", "r1") else -1.0
    assert {o.observer, o.target} == {"r0", "r1"}
    return sign * o.vector[0], sign * o.vector[1]


def _converged_estimate(t: float, std: float = 0.1) -> Estimate:
    cov = ((std**2, 0.0), (0.0, std**2))
    return Estimate(t, "pf_uv", "r0", {"r1": R1}, {"r1": cov})


def _check_counts(stage: DetectionAssociator) -> None:
    s = stage.stats
    assert s["proposed"] == s["accepted"] + s["rejected"]
    assert s["rejected"] == sum(s[k] for k in REJECTIONS)
    assert s["accepted"] == s["accepted_by_estimate"] + s["accepted_by_range"]


def test_two_objects_in_view_and_a_decoy_seen_by_one_robot() -> None:
    stage = DetectionAssociator(_team())
    _setup(stage)
    stage.process(_seen("r1", 1.0, ("chair", CHAIR_A), ("bottle", BOTTLE_B)))
    out = stage.process(
        _seen("r0", 1.04, ("chair", CHAIR_A), ("chair", CHAIR_C), ("bottle", BOTTLE_B))
    )
    obs = _observations(out)
    assert len(obs) == 2
    for o in obs:
        # the robot of the earlier frame observes: p_r0 - p_r1, at the later frame's time
        assert (o.observer, o.target) == ("r1", "r0")
        assert o.t == pytest.approx(1.04)
        assert _r1_minus_r0(o) == pytest.approx(R1, abs=1e-9)
        assert 0.15 < o.sigma < 0.4
    # chair A-A, chair C-A (passes the range gate, inconsistent with the other two), bottle B-B
    assert stage.stats["proposed"] == 3
    assert stage.stats["accepted"] == 2
    assert stage.stats["accepted_by_range"] == 2
    assert stage.stats["rejected_inconsistent"] == 1
    _check_counts(stage)


def test_decoy_alone_is_ambiguous_under_the_range_gate_but_rejected_by_the_estimate() -> None:
    # r1 sees only chair A; r0 sees chairs A and C. Both pairings match the range: ambiguous.
    stage = DetectionAssociator(_team())
    _setup(stage)
    stage.process(_seen("r1", 1.0, ("chair", CHAIR_A)))
    out = stage.process(_seen("r0", 1.05, ("chair", CHAIR_A), ("chair", CHAIR_C)))
    assert _observations(out) == []
    assert stage.stats["rejected_ambiguous"] == 2
    _check_counts(stage)
    # With a converged estimate, the estimate gate rejects the decoy and keeps the true pair.
    stage.feedback(_converged_estimate(1.1))
    stage.process(_seen("r1", 1.2, ("chair", CHAIR_A)))
    obs = _observations(stage.process(_seen("r0", 1.25, ("chair", CHAIR_A), ("chair", CHAIR_C))))
    assert len(obs) == 1
    assert _r1_minus_r0(obs[0]) == pytest.approx(R1, abs=1e-9)
    assert stage.stats["accepted_by_estimate"] == 1
    assert stage.stats["rejected_gate"] == 1
    _check_counts(stage)


def test_wrong_pairings_are_rejected_by_the_gates() -> None:
    other_chair = (2.5, -2.0)  # r1 sees a different chair than r0
    stage = DetectionAssociator(_team())
    _setup(stage)
    stage.process(_seen("r1", 1.0, ("chair", other_chair)))
    assert _observations(stage.process(_seen("r0", 1.05, ("chair", CHAIR_A)))) == []
    assert stage.stats["rejected_gate"] == 1  # implies 4.6 m against a 4.0 m range
    # A wrong pairing that the range gate cannot see (the implied vector has the range's length
    # but points 20 degrees off) is caught by the estimate once converged.
    stage.feedback(_converged_estimate(1.1))
    off = (4.0 * math.cos(math.radians(20)), 4.0 * math.sin(math.radians(20)))
    lookalike = (CHAIR_A[0] + R1[0] - off[0], CHAIR_A[1] + R1[1] - off[1])
    stage.process(_seen("r1", 1.2, ("chair", lookalike)))
    assert _observations(stage.process(_seen("r0", 1.25, ("chair", CHAIR_A)))) == []
    assert stage.stats["rejected_gate"] == 2
    assert stage.stats["accepted"] == 0
    _check_counts(stage)


def test_range_gate_removes_the_pair_bias() -> None:
    # The pair reads 0.25 m long; with no bias removed the true pair (4.0 m) would still pass a
    # 0.3 m gate, so narrow the gate to make the bias matter.
    stage = DetectionAssociator(_team(det_range_gate=0.1))
    _setup(stage)
    stage.process(_seen("r1", 1.0, ("chair", CHAIR_A)))
    assert len(_observations(stage.process(_seen("r0", 1.05, ("chair", CHAIR_A))))) == 1


def test_invalid_detections_are_rejected_and_counted() -> None:
    stage = DetectionAssociator(_team())
    _setup(stage)
    stage.process(
        DetectionEvent(
            1.0,
            "r1",
            (
                ObjectDetection("chair", math.nan, 0.5),  # no depth (NaN)
                ObjectDetection("chair", 0.0, 0.0, 0.0),  # the all-zero 'no depth' marker
            ),
        )
    )
    out = stage.process(_seen("r0", 1.05, ("chair", CHAIR_A)))
    assert _observations(out) == []
    assert stage.stats["invalid_object"] == 2
    assert stage.stats["objects"] == 1
    assert stage.stats["proposed"] == 0
    # an unknown robot's frame is counted and passed through
    ev = DetectionEvent(1.1, "r9", (ObjectDetection("chair", 1.0, 0.0),))
    assert stage.process(ev) == [ev]
    assert stage.stats["unknown_robot"] == 1


def test_events_pass_through_and_one_robot_is_never_paired_with_itself() -> None:
    stage = DetectionAssociator(_team())
    events: list[Event] = [
        OdometryEvent(0.0, "r0", 0.0, 0.0, 0.0),
        RangeEvent(0.0, "r0", "r1", 4.2, "n_0", "n_1"),
        GroundTruthEvent(0.0, "r0", (0.0, 0.0)),
        RelativeObservation(0.0, "r0", "r1", (4.0, 0.0), 0.2),
        _seen("r0", 0.1, ("chair", CHAIR_A)),
        _seen("r0", 0.15, ("chair", CHAIR_A)),  # same robot, within the window
    ]
    for ev in events:
        out = stage.process(ev)
        assert out[0] is ev
        assert len(out) == 1
    assert stage.stats["proposed"] == 0


def test_without_estimate_or_range_there_is_no_gate() -> None:
    stage = DetectionAssociator(_team())
    _setup(stage, with_range=False)
    stage.process(_seen("r1", 1.0, ("chair", CHAIR_A)))
    assert _observations(stage.process(_seen("r0", 1.05, ("chair", CHAIR_A)))) == []
    assert stage.stats["rejected_no_gate"] == 1
    # a range older than RANGE_MAX_AGE does not gate either
    stage.process(RangeEvent(1.1, "r0", "r1", 4.0 + BIAS, "n_0", "n_1"))
    stage.process(_seen("r1", 1.6, ("chair", CHAIR_A)))
    assert _observations(stage.process(_seen("r0", 1.65, ("chair", CHAIR_A)))) == []
    assert stage.stats["rejected_no_gate"] == 2


def test_no_odometry_means_no_heading() -> None:
    stage = DetectionAssociator(_team())
    stage.process(RangeEvent(1.0, "r0", "r1", 4.0 + BIAS, "n_0", "n_1"))
    stage.process(_seen("r1", 1.0, ("chair", CHAIR_A)))
    assert _observations(stage.process(_seen("r0", 1.05, ("chair", CHAIR_A)))) == []
    assert stage.stats["rejected_no_odometry"] == 1
    _check_counts(stage)


def test_frames_outside_the_window_are_not_paired_and_each_frame_pairs_once() -> None:
    stage = DetectionAssociator(_team(detection_window=0.1))
    _setup(stage)
    stage.process(_seen("r1", 1.0, ("chair", CHAIR_A)))
    assert _observations(stage.process(_seen("r0", 1.15, ("chair", CHAIR_A)))) == []
    assert stage.stats["proposed"] == 0
    stage.process(_seen("r1", 1.2, ("chair", CHAIR_A)))  # pairs with r0 at 1.15
    assert stage.stats["proposed"] == 1
    stage.process(_seen("r0", 1.25, ("chair", CHAIR_A)))  # r1@1.2 is taken by r0@1.15
    assert stage.stats["proposed"] == 1


def test_motion_between_the_two_captures_is_compensated() -> None:
    # r1 drives towards r0 at 1 m/s; its frame is captured 0.08 s before r0's.
    stage = DetectionAssociator(_team(det_range_gate=0.2))
    for t in np.arange(0.0, 1.3, 0.05):
        stage.process(OdometryEvent(float(t), "r0", 0.0, 0.0, 0.0))
        stage.process(OdometryEvent(float(t), "r1", 4.0 - (t - 1.0), 0.0, math.pi, v=1.0))
    stage.process(RangeEvent(1.05, "r0", "r1", 3.95 + BIAS, "n_0", "n_1"))
    r1_at = (4.0 - 0.0, 0.0)  # at t = 1.0
    dets = (ObjectDetection("chair", *_body(r1_at, math.pi, CHAIR_A)),)
    stage.process(DetectionEvent(1.0, "r1", dets))
    obs = _observations(stage.process(_seen("r0", 1.08, ("chair", CHAIR_A))))
    assert len(obs) == 1
    # p_r1(1.08) - p_r0 = (3.92, 0), not the (4, 0) of r1's capture time
    assert _r1_minus_r0(obs[0]) == pytest.approx((3.92, 0.0), abs=1e-6)


def test_sigma_grows_with_detection_distance() -> None:
    stage = DetectionAssociator(_team())
    _setup(stage)
    near, far = (2.0, 0.3), (1.0, 2.5)
    stage.process(_seen("r1", 1.0, ("cup", near), ("tv", far)))
    obs = _observations(stage.process(_seen("r0", 1.05, ("cup", near), ("tv", far))))
    by_sigma = sorted(obs, key=lambda o: o.sigma)
    assert len(by_sigma) == 2
    assert by_sigma[0].sigma < by_sigma[1].sigma
    assert by_sigma[0].sigma >= _team().association.sigma_det


def test_unlabelled_detections_match_any_label() -> None:
    stage = DetectionAssociator(_team())
    _setup(stage)
    stage.process(_seen("r1", 1.0, ("", CHAIR_A)))
    assert len(_observations(stage.process(_seen("r0", 1.05, ("chair", CHAIR_A))))) == 1


def test_nothing_wrong_gets_through_on_a_simulated_run() -> None:
    """Five robots, eight objects (two chairs), 30 s: every accepted pair is a true pair.

    Range gate only at first; from 10 s on the stage also gets estimates (the truth with a
    0.15 m standard deviation, as a converged filter would give).
    """
    sim = multi_scenario(seed=4, duration=30.0, detections=True)
    stage = DetectionAssociator(sim.config)
    errors = []
    next_estimate = 10.0
    for ev in sim.events():
        if isinstance(ev, GroundTruthEvent):
            continue
        if ev.t >= next_estimate:
            ref = sim.true_pose("r0", ev.t)
            positions = {}
            for r in sim.config.others:
                p = sim.true_pose(r, ev.t)
                positions[r] = (p[0] - ref[0], p[1] - ref[1])
            cov = ((0.15**2, 0.0), (0.0, 0.15**2))
            stage.feedback(Estimate(ev.t, "pf_uv", "r0", positions, dict.fromkeys(positions, cov)))
            next_estimate += 0.1
        for o in _observations(stage.process(ev)):
            pi, pj = sim.true_pose(o.observer, o.t), sim.true_pose(o.target, o.t)
            errors.append(math.hypot(o.vector[0] - (pj[0] - pi[0]), o.vector[1] - (pj[1] - pi[1])))
    s = stage.stats
    assert s["accepted_by_range"] > 20 and s["accepted_by_estimate"] > 50
    assert s["rejected"] > 0  # decoys and wrong pairings were proposed and turned down
    assert max(errors) < 0.6  # heading drift and depth noise, never another object (> 1 m)
    assert float(np.median(errors)) < 0.2
    _check_counts(stage)


def test_pf_uv_fuses_detections_in_the_filter() -> None:
    """Single range, static reference: detections give the bearing the range does not."""
    sim = single_scenario(seed=0, duration=25.0, detections=True)
    config = sim.config.with_filter(particles=3000)
    gt = GroundTruth("r0")
    engine = Engine(
        [build_pipeline(m, config, seed=0) for m in ("pf", "pf_uv")], truth_sinks=[gt.add]
    )
    engine.run(sim.events())
    report = evaluate(engine, gt, "single", warmup=10.0)
    stats = engine.pipelines[1].stats()
    assert stats["DetectionAssociator.accepted"] > 10
    assert stats["relative"] == stats["DetectionAssociator.accepted"]  # all fused, none late
    pf, pf_uv = (report.methods[m].robots["r1"].median for m in ("pf", "pf_uv"))
    assert pf_uv < 0.1
    assert pf_uv < pf


def test_refuses_a_filter_that_estimates_the_headings() -> None:
    with pytest.raises(ValueError, match="heading_mode"):
        DetectionAssociator(_team().with_filter(heading_mode="estimate"))


def test_sigma_grows_with_the_time_a_robot_has_driven() -> None:
    """Odometry headings drift while robots move: later detection vectors weigh less."""

    def sigma_after(drive_s: float) -> float:
        stage = DetectionAssociator(_team())
        times = np.arange(0.0, drive_s + 1.0, 0.05)
        for t in times:
            stage.process(OdometryEvent(float(t), "r0", 0.0, 0.0, 0.0))
            # r1 turns on the spot (pose and twist change) until drive_s, then stands
            yaw = math.pi + 0.01 * min(float(t), drive_s)
            stage.process(OdometryEvent(float(t), "r1", *R1, yaw, w=0.01 if t < drive_s else 0.0))
        t0 = float(times[-1])
        stage.process(RangeEvent(t0, "r0", "r1", 4.0 + BIAS, "n_0", "n_1"))
        yaw = math.pi + 0.01 * drive_s
        dets = (ObjectDetection("chair", *_body(R1, yaw, CHAIR_A)),)
        stage.process(DetectionEvent(t0, "r1", dets))
        obs = _observations(stage.process(_seen("r0", t0 + 0.01, ("chair", CHAIR_A))))
        assert len(obs) == 1
        return obs[0].sigma

    assert sigma_after(0.0) < sigma_after(30.0) < sigma_after(90.0)
