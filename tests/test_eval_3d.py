"""Evaluation and outputs of a flying team's 3D estimates, against hand-made truths.

The truth: the reference r0 at (1, 2, 1.5) with a yaw of 30 deg, r1 and r2 placed so that in
r0's yaw-only body frame (z up) they are at (2, 1, 0.5) and (-1, 3, -1), with yaws of +40 and
-100 deg relative to r0's. The estimates are off by known 3D offsets and yaw errors, so every
figure is one computed by hand. 2D estimates of the same truth score as they always did.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from relloc.config import RobotConfig, TeamConfig
from relloc.estimate import BODY_FRAME, Estimate
from relloc.evaluation.consistency import CHI2_2D_95, CHI2_3D_95, consistency
from relloc.evaluation.metric import METRICS, MethodRun
from relloc.evaluation.metrics import (
    GroundTruth,
    align,
    associate,
    ate,
    orthogonal_procrustes,
    truth_in_frame,
    umeyama_se2,
)
from relloc.evaluation.report import MethodReport, ScenarioReport, published_yaws
from relloc.events import GroundTruthEvent
from relloc.ros import messages as rm
from relloc.ros.estimate_msgs import NOT_ESTIMATED, estimate_pose_cdr, estimate_pose_msg
from relloc.sinks.tum import write_tum
from relloc.sinks.zenoh_sink import ZenohSink
from relloc.sources.rosbag import RosbagSource

REF_YAW = math.radians(30.0)
REF = (1.0, 2.0, 1.5)
BODY = {"r1": (2.0, 1.0, 0.5), "r2": (-1.0, 3.0, -1.0)}
"""Each robot's true position in r0's yaw-only body frame."""
REL_YAW = {"r1": math.radians(40.0), "r2": math.radians(-100.0)}
"""Each robot's true yaw relative to r0's."""
OFFSET = {"r1": (0.3, 0.0, 0.4), "r2": (0.0, 0.6, -0.8)}
"""Estimate minus truth: APE 0.5 m for r1, 1.0 m for r2."""
YAW_ERROR = {"r1": math.radians(5.0), "r2": math.radians(-10.0)}
COV = {"r1": ((0.03, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 0.04)), "r2": np.eye(3).tolist()}
"""r1's NEES: 0.09 / 0.03 + 0.16 / 0.04 = 7, inside the 3-dof 95 % bound (7.81) though
outside the 2-dof one (5.99); r2's 0.36 + 0.64 = 1."""
TIMES = [float(t) for t in range(11)]


def world(robot: str) -> tuple[tuple[float, float, float], float]:
    """``robot``'s true world position and yaw."""
    if robot == "r0":
        return REF, REF_YAW
    bx, by, bz = BODY[robot]
    c, s = math.cos(REF_YAW), math.sin(REF_YAW)
    position = (REF[0] + c * bx - s * by, REF[1] + s * bx + c * by, REF[2] + bz)
    return position, REF_YAW + REL_YAW[robot]


def truth() -> GroundTruth:
    gt = GroundTruth("r0")
    for t in TIMES:
        for robot in ("r0", "r1", "r2"):
            position, yaw = world(robot)
            gt.add(GroundTruthEvent(t, robot, position, yaw))
    return gt


def estimate(t: float) -> Estimate:
    """A 3D body-frame estimate off by :data:`OFFSET` and :data:`YAW_ERROR`."""
    positions = {r: tuple(b + o for b, o in zip(BODY[r], OFFSET[r], strict=True)) for r in BODY}
    return Estimate(
        t,
        "pf",
        "r0",
        positions,
        {r: tuple(tuple(row) for row in COV[r]) for r in BODY},
        frame=BODY_FRAME,
        yaws={r: (REL_YAW[r] + YAW_ERROR[r], 0.1) for r in BODY},
    )


def method_run(estimates: list[Estimate]) -> MethodRun:
    gt = truth()
    robots = ["r1", "r2"]
    return MethodRun("pf", estimates, gt, robots, 0.0, 2.0, associate(estimates, gt, robots))


def method_report(estimates: list[Estimate]) -> MethodReport:
    run = method_run(estimates)
    results = {metric.name: metric().compute(run) for metric in METRICS}
    return MethodReport(
        results,
        run.paired,
        frame=BODY_FRAME,
        published=run.published,
        published_yaws=published_yaws(run.shown, run.published),
    )


# ---------------------------------------------------------------------------- truth, scores
def test_body_frame_truth_is_yaw_only_with_the_height_kept() -> None:
    gt = truth()
    est = estimate(3.0)
    for robot, body in BODY.items():
        assert truth_in_frame(est, gt, robot) == pytest.approx(body, abs=1e-12)
    assert gt.height_at("r1", 3.0) == pytest.approx(2.0)
    # A 2D estimate of the same truth: its own 2 coordinates, the height left out.
    flat = Estimate(3.0, "pf", "r0", {"r1": (2.0, 1.0)}, frame=BODY_FRAME)
    assert truth_in_frame(flat, gt, "r1") == pytest.approx((2.0, 1.0), abs=1e-12)


def test_json_of_a_3d_run_has_the_2d_keys_with_hand_computed_values() -> None:
    report = method_report([estimate(t) for t in TIMES])
    robots = report.to_json()["robots"]
    for robot, ape in (("r1", 0.5), ("r2", 1.0)):
        fields = robots[robot]
        assert fields["ape_median"] == pytest.approx(ape)
        assert fields["ape_mean"] == pytest.approx(ape)
        assert fields["n"] == 9  # after the 2 s warm-up
        assert fields["yaw_error_median_deg"] == pytest.approx(abs(math.degrees(YAW_ERROR[robot])))
        assert fields["yaw_error_mean_deg"] == pytest.approx(abs(math.degrees(YAW_ERROR[robot])))
        assert fields["coverage95"] == 1.0
        assert fields["ate_rmse"] == pytest.approx(0.0, abs=1e-9)  # a constant offset
        assert fields["run_aligned_ape_median"] is not None
        assert fields["step_aligned_ape_median"] is not None
    assert robots["r1"]["nees_median"] == pytest.approx(7.0)
    assert robots["r2"]["nees_median"] == pytest.approx(1.0)


def test_coverage_counts_3_degrees_of_freedom() -> None:
    c = consistency([estimate(t) for t in TIMES], truth(), ["r1"], 0.0)["r1"]
    assert c.dof == 3
    np.testing.assert_allclose(c.nees, 7.0)
    assert CHI2_2D_95 < 7.0 < CHI2_3D_95
    assert c.coverage == 1.0


def test_alignments_turn_about_z_only() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    c, s = math.cos(0.7), math.sin(0.7)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    dst = src @ turn.T + np.array([0.5, -1.0, 2.0])
    r, t = umeyama_se2(src, dst)
    np.testing.assert_allclose(r, turn, atol=1e-12)
    np.testing.assert_allclose(t, [0.5, -1.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(orthogonal_procrustes(src, src @ turn.T), turn, atol=1e-12)
    paired = associate([estimate(t) for t in TIMES], truth(), ["r1"])
    assert ate(paired["r1"]) == pytest.approx(0.0, abs=1e-9)
    for mode in ("run", "step"):
        assert align(paired, mode)["r1"].est.shape == (len(TIMES), 3)


# ---------------------------------------------------------------------------- 2D unchanged
def test_2d_estimates_score_as_before_against_a_3d_truth() -> None:
    gt = truth()
    flat = [
        Estimate(
            t,
            "pf",
            "r0",
            {"r1": (2.3, 1.4)},
            {"r1": ((0.09, 0.0), (0.0, 0.04))},
            frame=BODY_FRAME,
            yaws={"r1": (0.5, 0.1)},
        )
        for t in TIMES
    ]
    p = associate(flat, gt, ["r1"])["r1"]
    assert p.est.shape == p.gt.shape == (len(TIMES), 2)
    np.testing.assert_allclose(p.errors, 0.5)  # (0.3, 0.4) in the plane
    c = consistency(flat, gt, ["r1"], 0.0)["r1"]
    assert c.dof == 2
    np.testing.assert_allclose(c.nees, 5.0)
    assert c.coverage == 1.0  # 5 <= 5.99
    # The 2D fits are the planar Kabsch of before, to the bit.
    rng = np.random.default_rng(2)
    src, dst = rng.normal(size=(12, 2)), rng.normal(size=(12, 2))
    u, _, vt = np.linalg.svd(dst.T @ src)
    assert np.array_equal(orthogonal_procrustes(src, dst), u @ vt)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((dst - mu_d).T @ (src - mu_s))
    r = u @ np.diag([1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    got_r, got_t = umeyama_se2(src, dst)
    assert np.array_equal(got_r, r) and np.array_equal(got_t, mu_d - r @ mu_s)
    # A 2D estimate publishes its heading, not a tag yaw: here none, the identity as before.
    assert estimate_pose_msg(flat[0], "r1").pose.pose.orientation.w == 1.0
    assert estimate_pose_msg(flat[0], "r1").pose.covariance[35] == NOT_ESTIMATED


# ---------------------------------------------------------------------------- outputs
def test_tum_lines_carry_z_and_the_published_yaw(tmp_path: Path) -> None:
    report = method_report([estimate(t) for t in TIMES])
    shown = report.published["r1"]
    path = tmp_path / "pf_r1.txt"
    write_tum(path, shown.t, shown.est, yaws=report.published_yaws["r1"])
    yaw = REL_YAW["r1"] + YAW_ERROR["r1"]
    x, y, z = (b + o for b, o in zip(BODY["r1"], OFFSET["r1"], strict=True))
    qz, qw = math.sin(yaw / 2), math.cos(yaw / 2)
    lines = path.read_text().splitlines()
    assert lines[1] == f"0.000000 {x:.6f} {y:.6f} {z:.6f} 0 0 {qz:.6f} {qw:.6f}"
    # 2D: z = 0 and the identity, as always.
    flat = tmp_path / "flat.txt"
    write_tum(flat, np.array([1.0]), np.array([[2.0, 1.0]]))
    assert flat.read_text().splitlines()[1] == "1.000000 2.000000 1.000000 0 0 0 0 1"


class _Session:
    """A Zenoh session that keeps what is put: ``key -> [payload]``."""

    def __init__(self) -> None:
        self.puts: dict[str, list[bytes]] = {}

    def declare_publisher(self, key: str) -> Any:
        puts = self.puts.setdefault(key, [])
        return SimpleNamespace(put=lambda payload, attachment=None: puts.append(bytes(payload)))


def test_pose_message_has_z_the_3x3_covariance_and_the_yaw_variance(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from relloc.sinks.mcap import write_mcap

    est = estimate(4.0)
    msg = estimate_pose_msg(est, "r1")
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    assert (p.x, p.y, p.z) == pytest.approx((2.3, 1.0, 0.9))
    yaw = REL_YAW["r1"] + YAW_ERROR["r1"]
    assert (q.z, q.w) == pytest.approx((math.sin(yaw / 2), math.cos(yaw / 2)))
    expected = np.diag([0.0, 0.0, 0.0, NOT_ESTIMATED, NOT_ESTIMATED, 0.1**2])
    expected[:3, :3] = COV["r1"]
    np.testing.assert_array_equal(np.asarray(msg.pose.covariance).reshape(6, 6), expected)

    wire = estimate_pose_cdr(est, "r1")
    assert wire == rm.encode(msg, rm.POSE_WITH_COVARIANCE_STAMPED)
    config = TeamConfig(
        robots=tuple(RobotConfig(name=r) for r in ("r0", "r1", "r2")), reference="r0"
    )
    session = _Session()
    sink = ZenohSink(session, config)
    sink(est)
    assert session.puts[sink.key("r1", "pf")][-1] == wire

    report = ScenarioReport("s", 2.0, 10.0, {"pf": method_report([est])}, reference="r0")
    engine = SimpleNamespace(pipelines=[SimpleNamespace(name="pf", estimates=[est])])
    path = write_mcap(tmp_path / "e.mcap", engine, report, distro="jazzy")  # type: ignore[arg-type]
    found: dict[str, Any] = {}
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages():
            found[channel.topic] = decoded
    recorded = found["/relloc/pf/r1/pose"].pose
    assert recorded.pose.position.z == pytest.approx(0.9)
    assert recorded.covariance[35] == pytest.approx(0.01)
    truth_pose = found["/relloc/truth/r1/pose"].pose.position
    assert (truth_pose.x, truth_pose.y, truth_pose.z) == pytest.approx(BODY["r1"])


def test_rosbag_motion_capture_keeps_the_height_for_a_3d_team(
    tmp_path: Path, bag_writer: Callable[..., Path]
) -> None:
    types = rm.typestore().types

    def pose(t: float, x: float, y: float, z: float, yaw: float) -> Any:
        header = types["std_msgs/msg/Header"](stamp=rm.time_msg(t), frame_id="world")
        point = types["geometry_msgs/msg/Point"](x=x, y=y, z=z)
        body = types["geometry_msgs/msg/Pose"](
            position=point, orientation=rm.quaternion_from_yaw(yaw)
        )
        return types[rm.POSE_STAMPED](header=header, pose=body)

    messages = [
        (
            "/vrpn_client_node/b1/pose",
            rm.POSE_STAMPED,
            100.0 + k,
            pose(100.0 + k, 1.0, 2.0, 1.5, 0.5),
        )
        for k in range(3)
    ]
    path = bag_writer(tmp_path / "flying", messages)
    robots = (RobotConfig(name="r1", mocap_body="b1"), RobotConfig(name="r2"))
    for dimension, position in ((3, (1.0, 2.0, 1.5)), (2, (1.0, 2.0))):
        config = TeamConfig(robots=robots, reference="r1", dimension=dimension)
        source = RosbagSource(path, config, detections=False, ranges=False, odometry=False)
        events = [e for e in source if isinstance(e, GroundTruthEvent)]
        assert len(events) == 3
        assert events[0].position == pytest.approx(position)
        assert len(events[0].position) == dimension
        assert events[0].yaw == pytest.approx(0.5)
