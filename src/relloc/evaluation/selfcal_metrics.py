"""Self-calibration against motion capture: published headings and range biases.

The truth of a relative heading is a rotation between odometry frames, fixed in the world by
:func:`odometry_frame_rotation`; :func:`associate_headings` pairs every published heading with
it, :func:`bias_errors` every published range bias with a known true one. Scored by
:mod:`relloc.evaluation.selfcal_scores`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from relloc.estimate import Estimate
from relloc.evaluation.metrics import FloatArray, GroundTruth
from relloc.odometry import wrap_angle


def nearest_pose(
    gt: GroundTruth, robot: str, t: float, max_gap: float = 0.5
) -> tuple[float, float, float] | None:
    """The motion-capture pose at ``t`` (interpolated), else the nearest sample within ``max_gap``."""
    pose = gt.pose_at(robot, t)
    if pose is not None:
        return pose
    times, poses = gt.trajectory(robot)
    if times.size == 0:
        return None
    i = int(np.argmin(np.abs(times - t)))
    if abs(times[i] - t) > max_gap:
        return None
    return float(poses[i, 0]), float(poses[i, 1]), float(poses[i, 2])


def odometry_frame_rotation(
    gt: GroundTruth, robot: str, odometry: tuple[float, float]
) -> float | None:
    """Rotation of ``robot``'s odometry frame in the world (mocap) frame (rad): its mocap yaw
    minus its odometry yaw ``odometry = (t, yaw)``, taken at its first odometry message (the
    odometry frame is fixed; later the odometry yaw drifts, not the frame). Evaluation only."""
    t, yaw = odometry
    pose = nearest_pose(gt, robot, t)
    if pose is None:
        return None
    return float(wrap_angle(pose[2] - yaw))


@dataclass
class HeadingPaired:
    """Published relative headings of one robot against the truth: times, mean, spread, truth (rad)."""

    t: FloatArray
    mean: FloatArray
    spread: FloatArray
    truth: FloatArray

    @property
    def errors(self) -> FloatArray:
        """Absolute wrapped error (rad)."""
        return np.abs(wrap_angle(self.mean - self.truth)) if len(self.t) else np.zeros(0)


def associate_headings(
    estimates: Sequence[Estimate],
    gt: GroundTruth,
    odometry_yaws: Mapping[str, Iterable[tuple[float, float]]],
    frame_rotation: float,
) -> dict[str, HeadingPaired]:
    """Pair every published relative heading with its truth.

    The estimates' frame is the reference's odometry frame, fixed in the world at
    ``frame_rotation`` (:func:`odometry_frame_rotation` at its first odometry message). The
    truth of robot ``i`` at ``t`` is the rotation that takes its odometry increments *now* into
    that frame: ``mocap_yaw_i(t) - odometry_yaw_i(t) - frame_rotation``; it drifts with the
    robot's gyro error, as the filter's estimate is meant to.
    """
    out: dict[str, HeadingPaired] = {}
    robots = sorted({r for est in estimates for r in est.headings})
    for robot in robots:
        yaws = dict(odometry_yaws.get(robot, []))
        t, m, s, g = [], [], [], []
        for est in estimates:
            if robot not in est.headings or est.t not in yaws:
                continue
            pose = gt.pose_at(robot, est.t)
            if pose is None:
                continue
            t.append(est.t)
            m.append(est.headings[robot][0])
            s.append(est.headings[robot][1])
            g.append(float(wrap_angle(pose[2] - yaws[est.t] - frame_rotation)))
        out[robot] = HeadingPaired(np.array(t), np.array(m), np.array(s), np.array(g))
    return out


def bias_errors(
    estimates: Sequence[Estimate], truth: dict[str, float], t_start: float
) -> dict[str, FloatArray]:
    """Per node pair with a known true bias: ``|published mean - truth|`` at every estimate
    from ``t_start`` on."""
    out: dict[str, list[float]] = {}
    for est in estimates:
        if est.t < t_start:
            continue
        for pair, (mean, _) in est.biases.items():
            if pair in truth:
                out.setdefault(pair, []).append(abs(mean - truth[pair]))
    return {k: np.array(v) for k, v in out.items()}


BIAS_Z95 = 1.959964
"""Half-width of a two-sided 95 % Gaussian interval, in standard deviations."""


def bias_coverage(
    estimates: Sequence[Estimate], truth: dict[str, float], t_start: float
) -> dict[str, FloatArray]:
    """Per node pair with a known true bias: at every estimate from ``t_start`` on, whether the
    published 95 % interval (mean +- 1.96 std) holds the truth (1.0) or not (0.0): whether the
    published std is honest, as the position coverage asks of a covariance."""
    out: dict[str, list[float]] = {}
    for est in estimates:
        if est.t < t_start:
            continue
        for pair, (mean, std) in est.biases.items():
            if pair in truth:
                out.setdefault(pair, []).append(float(abs(mean - truth[pair]) <= BIAS_Z95 * std))
    return {k: np.array(v) for k, v in out.items()}
