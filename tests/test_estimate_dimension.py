"""Positions carry their dimension: an :class:`Estimate` in 3D reaches the pose message, its
CDR bytes and a TUM file with its height and the z block of its covariance, and the 2D
outputs are what they were; a ground-truth pose carries its position as a tuple too."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from relloc.estimate import Estimate, covariance_of, position_of
from relloc.evaluation.metrics import GroundTruth
from relloc.events import GroundTruthEvent
from relloc.ros import messages as rm
from relloc.ros.estimate_msgs import NOT_ESTIMATED, estimate_pose, estimate_pose_cdr
from relloc.sinks.tum import write_tum

COV3 = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, 0.003], [0.002, 0.003, 0.16]])


def _estimate(dim: int) -> Estimate:
    p = np.array([1.5, -2.0, 0.7])[:dim]
    return Estimate(
        12.5,
        "pf",
        "r0",
        {"r1": position_of(p)},
        {"r1": covariance_of(COV3[:dim, :dim])},
    )


def test_a_3d_estimate_publishes_its_height_and_its_covariance() -> None:
    est = _estimate(3)
    assert est.dimension == 3
    assert np.array_equal(est.position("r1"), [1.5, -2.0, 0.7])
    cov = est.covariance("r1")
    assert cov is not None and np.array_equal(cov, COV3)
    pose = estimate_pose(est, "r1")
    assert (pose.x, pose.y, pose.z) == (1.5, -2.0, 0.7)
    full = np.array(pose.covariance).reshape(6, 6)
    assert np.array_equal(full[:3, :3], COV3)
    assert full[3, 3] == full[4, 4] == full[5, 5] == NOT_ESTIMATED
    msg = rm.decode(estimate_pose_cdr(est, "r1"), "geometry_msgs/msg/PoseWithCovarianceStamped")
    assert msg.pose.pose.position.z == 0.7
    assert np.array_equal(np.array(msg.pose.covariance), full.ravel())


def test_a_2d_estimate_keeps_z_not_estimated() -> None:
    est = _estimate(2)
    assert est.dimension == 2
    full = np.array(estimate_pose(est, "r1").covariance).reshape(6, 6)
    assert np.array_equal(full[:2, :2], COV3[:2, :2])
    assert full[2, 2] == NOT_ESTIMATED and estimate_pose(est, "r1").z == 0.0


def test_tum_files_carry_z_in_3d_and_0_in_2d(tmp_path: Path) -> None:
    times = np.array([1.0, 2.0])
    write_tum(tmp_path / "a.txt", times, np.array([[1.0, 2.0], [3.0, 4.0]]))
    write_tum(tmp_path / "b.txt", times, np.array([[1.0, 2.0, 0.5], [3.0, 4.0, 0.25]]))
    two = (tmp_path / "a.txt").read_text().splitlines()[1]
    three = (tmp_path / "b.txt").read_text().splitlines()[1]
    assert two == "1.000000 1.000000 2.000000 0 0 0 0 1"
    assert three == "1.000000 1.000000 2.000000 0.500000 0 0 0 1"


def test_a_2d_ground_truth_position_flows_through_ground_truth_unchanged() -> None:
    a = GroundTruthEvent(3.0, "a", (1.25, -0.5), 0.3)
    b = GroundTruthEvent(3.0, "b", (4.0, 2.75), -1.0)
    assert rm.pose_to_ground_truth(rm.pose_stamped_msg(a), "a") == a  # the message round trip
    gt = GroundTruth("a")
    gt.add(a)
    gt.add(b)
    assert gt.pose_at("a", 3.0) == (1.25, -0.5, 0.3)
    assert gt.relative_at("b", 3.0) == (4.0 - 1.25, 2.75 + 0.5)
    times, poses = gt.trajectory("b")
    assert times.tolist() == [3.0] and poses.tolist() == [[4.0, 2.75, -1.0]]
