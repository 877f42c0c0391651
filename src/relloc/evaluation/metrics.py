"""Evaluation against motion capture: APE, ATE, convergence time.

Definitions follow evo (MichaelGrupp/evo), applied to *relative* positions:

* **APE** of robot ``i`` at an estimate time ``t``: ``|| p_hat_i(t) - (g_i(t) - g_ref(t)) ||``
  where ``g`` is the motion-capture position interpolated at ``t`` (linear, only across gaps
  shorter than ``max_gap``), in the frame the estimate names (the shared heading frame, or the reference's body frame). Reported as median, mean, RMSE, std
  and max over the estimates after a warm-up window. The particle filter is never aligned.
* **ATE** of a trajectory: the APE RMSE after aligning the whole estimated relative trajectory
  of one robot to ground truth with one rigid 2-D transform (rotation + translation, Umeyama /
  Kabsch, no scale): it measures the shape of the path, forgiving a constant offset.
* **Multilateration** knows the formation only up to rotation and reflection: its fair figure
  uses *one* orthogonal transform (rotation or reflection about the reference) fitted to the
  whole run (``align="run"``); the per-step fit (``align="step"``) is an oracle that uses
  ground truth at every step and is reported as such.
* **Convergence time**: the first estimate time after which at most 5 % of estimates have a
  worst-robot APE above ``threshold`` (0.3 m by default).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from relloc.estimate import BODY_FRAME, HEADING_FRAME, Estimate
from relloc.events import GroundTruthEvent
from relloc.odometry import wrap_angle

FloatArray = NDArray[np.float64]


class GroundTruth:
    """Motion-capture tracks of the robots, interpolated with a bounded gap."""

    def __init__(self, reference: str, max_gap: float = 0.25) -> None:
        self.reference = reference
        self.max_gap = max_gap
        self._t: dict[str, list[float]] = {}
        self._xy: dict[str, list[tuple[float, float, float]]] = {}
        self._sorted = True

    def add(self, ev: GroundTruthEvent) -> None:
        ts = self._t.setdefault(ev.robot, [])
        if ts and ev.t < ts[-1]:
            self._sorted = False
        ts.append(ev.t)
        self._xy.setdefault(ev.robot, []).append((ev.x, ev.y, ev.yaw))

    def _sort(self) -> None:
        if self._sorted:
            return
        for r in self._t:
            order = np.argsort(self._t[r], kind="stable")
            self._t[r] = [self._t[r][i] for i in order]
            self._xy[r] = [self._xy[r][i] for i in order]
        self._sorted = True

    @property
    def robots(self) -> list[str]:
        return list(self._t)

    def pose_at(self, robot: str, t: float) -> tuple[float, float, float] | None:
        """World pose ``(x, y, yaw)`` at ``t``, or None outside the track or across a long gap."""
        self._sort()
        ts = self._t.get(robot)
        if not ts or t < ts[0] or t > ts[-1]:
            return None
        i = bisect.bisect_left(ts, t)
        if ts[i] == t:
            return self._xy[robot][i]
        a, b = i - 1, i
        if ts[b] - ts[a] > self.max_gap:
            return None
        f = (t - ts[a]) / (ts[b] - ts[a])
        (xa, ya, wa), (xb, yb, wb) = self._xy[robot][a], self._xy[robot][b]
        return xa + f * (xb - xa), ya + f * (yb - ya), wa + f * math.remainder(wb - wa, math.tau)

    def relative_at(self, robot: str, t: float) -> tuple[float, float] | None:
        """``g_robot(t) - g_reference(t)`` in the world frame, or None if either is unknown."""
        p, q = self.pose_at(robot, t), self.pose_at(self.reference, t)
        if p is None or q is None:
            return None
        return p[0] - q[0], p[1] - q[1]

    def trajectory(self, robot: str) -> tuple[FloatArray, FloatArray]:
        self._sort()
        return np.array(self._t.get(robot, [])), np.array(self._xy.get(robot, [])).reshape(-1, 3)


@dataclass(frozen=True)
class ApeStats:
    median: float
    mean: float
    rmse: float
    std: float
    max: float
    n: int

    @classmethod
    def of(cls, errors: FloatArray) -> ApeStats:
        e = np.asarray(errors, dtype=float)
        if e.size == 0:
            return cls(math.nan, math.nan, math.nan, math.nan, math.nan, 0)
        return cls(
            float(np.median(e)),
            float(np.mean(e)),
            float(np.sqrt(np.mean(e**2))),
            float(np.std(e)),
            float(np.max(e)),
            int(e.size),
        )


@dataclass
class Paired:
    """Estimates of one robot associated with ground truth: times, estimates, truths (K, 2)."""

    t: FloatArray
    est: FloatArray
    gt: FloatArray
    std: FloatArray

    @property
    def errors(self) -> FloatArray:
        return np.linalg.norm(self.est - self.gt, axis=1) if len(self.t) else np.zeros(0)


def associate(
    estimates: Sequence[Estimate],
    gt: GroundTruth,
    robots: Iterable[str],
    rotation: float = 0.0,
) -> dict[str, Paired]:
    """Pair every estimate of every robot with interpolated relative ground truth, in the
    estimate's frame (:func:`truth_in_frame`; ``rotation``: that of its heading frame)."""
    out: dict[str, Paired] = {}
    for robot in robots:
        t, e, g, s = [], [], [], []
        for est in estimates:
            if robot not in est.positions:
                continue
            truth = truth_in_frame(est, gt, robot, rotation)
            if truth is None:
                continue
            t.append(est.t)
            e.append(est.positions[robot])
            g.append(truth)
            s.append(est.std(robot))
        out[robot] = Paired(
            np.array(t), np.array(e).reshape(-1, 2), np.array(g).reshape(-1, 2), np.array(s)
        )
    return out


def truth_in_frame(
    est: Estimate, gt: GroundTruth, robot: str, rotation: float = 0.0
) -> tuple[float, float] | None:
    """``robot``'s true position relative to the reference at ``est.t`` in the frame the
    estimate is in (:attr:`Estimate.frame`): the reference's body frame (turned by its
    motion-capture yaw then), or the heading frame, the world turned by ``rotation`` (rad; the
    compass frame: 0). ``None`` where the truth is unknown."""
    truth = gt.relative_at(robot, est.t)
    if truth is None:
        return None
    if est.frame == BODY_FRAME:
        pose = gt.pose_at(gt.reference, est.t)
        if pose is None:
            return None
        rotation = pose[2]
    return _to_body(truth, rotation) if rotation != 0.0 else truth


def orthogonal_procrustes(src: FloatArray, dst: FloatArray) -> FloatArray:
    """The 2x2 orthogonal matrix (rotation or reflection) minimising ``||src R^T - dst||``."""
    u, _, vt = np.linalg.svd(dst.T @ src)
    return u @ vt


def umeyama_se2(src: FloatArray, dst: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotation R (proper) and translation t minimising ``||src R^T + t - dst||``."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    h = (dst - mu_d).T @ (src - mu_s)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(u @ vt))
    r = u @ np.diag([1.0, d]) @ vt
    return r, mu_d - r @ mu_s


def align(paired: dict[str, Paired], mode: str) -> dict[str, Paired]:
    """Align estimates about the reference: ``"run"`` one orthogonal map, ``"step"`` one per time."""
    if mode == "none":
        return paired
    if mode == "run":
        src = np.concatenate([p.est for p in paired.values()]) if paired else np.zeros((0, 2))
        dst = np.concatenate([p.gt for p in paired.values()]) if paired else np.zeros((0, 2))
        if len(src) < 2:
            return paired
        r = orthogonal_procrustes(src, dst)
        return {k: Paired(p.t, p.est @ r.T, p.gt, p.std) for k, p in paired.items()}
    if mode == "step":
        times = sorted({float(t) for p in paired.values() for t in p.t})
        out = {k: Paired(p.t, p.est.copy(), p.gt, p.std) for k, p in paired.items()}
        for t in times:
            rows = {k: np.flatnonzero(p.t == t) for k, p in out.items()}
            src = np.concatenate([out[k].est[i] for k, i in rows.items()])
            dst = np.concatenate([out[k].gt[i] for k, i in rows.items()])
            if len(src) < 2:
                continue
            r = orthogonal_procrustes(src, dst)
            for k, i in rows.items():
                out[k].est[i] = out[k].est[i] @ r.T
        return out
    raise ValueError(f"unknown alignment {mode!r}")


def ate(p: Paired) -> float:
    """ATE (RMSE) of one robot's relative trajectory after one SE(2) alignment."""
    if len(p.t) < 2:
        return math.nan
    r, t = umeyama_se2(p.est, p.gt)
    return float(np.sqrt(np.mean(np.sum((p.est @ r.T + t - p.gt) ** 2, axis=1))))


CONVERGENCE_THRESHOLD_M = 0.3
"""Worst-robot APE under which a run counts as converged (m)."""
CONVERGENCE_TOLERANCE = 0.05
"""Fraction of the estimates after the convergence time allowed above the threshold."""
CONVERGENCE_HOLD_S = 1.0
"""The worst-robot APE must stay under the threshold for this long from the convergence time on
(within the tolerance): one lucky estimate inside a bad first second is not convergence."""
CONVERGENCE_MIN_REST = 0.1
"""The convergence time must leave at least this fraction of the estimates' time span after it:
a good last estimate alone says nothing."""


def convergence_time(
    paired: dict[str, Paired],
    threshold: float = CONVERGENCE_THRESHOLD_M,
    tolerance: float = CONVERGENCE_TOLERANCE,
    start: float | None = None,
    hold: float = CONVERGENCE_HOLD_S,
    min_rest: float = CONVERGENCE_MIN_REST,
) -> float:
    """Seconds from ``start`` (default: the first estimate) to the convergence time: the first
    estimate time from which the worst-robot APE stays under ``threshold`` for ``hold`` seconds
    and for at least ``1 - tolerance`` of the estimates up to the end, with at least
    ``min_rest`` of the estimates' time span still to come. NaN if that never happens.

    The worst-robot APE at an estimate time is the largest error of any robot estimated then.
    Counting only the rest of the run is not enough: a run whose robots are 4 m off during its
    first second would "converge" at 0 s, because one second is under 5 % of a minute.
    """
    if not paired:
        return math.nan
    times = np.array(sorted({float(t) for p in paired.values() for t in p.t}))
    if times.size == 0:
        return math.nan
    worst = np.zeros(times.size)
    for p in paired.values():
        idx = np.searchsorted(times, p.t)
        np.maximum.at(worst, idx, p.errors)
    bad = worst > threshold
    n_bad = np.concatenate(([0], np.cumsum(bad)))  # n_bad[i]: bad estimates before index i
    index = np.arange(times.size)
    tail_bad = (n_bad[-1] - n_bad[:-1]) / (times.size - index)
    stop = np.searchsorted(times, times + hold, side="right")  # end of each hold window
    hold_bad = (n_bad[stop] - n_bad[:-1]) / (stop - index)
    early = times <= times[-1] - min_rest * (times[-1] - times[0])
    ok = np.flatnonzero(~bad & (hold_bad <= tolerance) & (tail_bad <= tolerance) & early)
    if ok.size == 0:
        return math.nan
    origin = times[0] if start is None else start
    return float(times[ok[0]] - origin)


def after(p: Paired, t_start: float) -> Paired:
    """The part of ``p`` at or after ``t_start``."""
    keep = p.t >= t_start
    return Paired(p.t[keep], p.est[keep], p.gt[keep], p.std[keep])


# ---------------------------------------------------------------------------- self-calibration
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


CHI2_2D_95 = 5.991464547107979
"""95 % quantile of the chi-square distribution with 2 degrees of freedom: the squared
Mahalanobis radius of a 2D 95 % ellipse."""


@dataclass
class Consistency:
    """Whether the published covariances cover the error: per estimate the normalised
    estimation error squared ``NEES = e^T C^-1 e`` (2 degrees of freedom: mean 2 for a
    consistent filter) and whether the truth lies in the 95 % ellipse (``NEES <= 5.99``)."""

    t: FloatArray
    nees: FloatArray

    @property
    def coverage(self) -> float:
        """Fraction of the estimates whose 95 % ellipse holds the truth."""
        return float(np.mean(self.nees <= CHI2_2D_95)) if self.nees.size else math.nan

    @property
    def nees_median(self) -> float:
        return float(np.median(self.nees)) if self.nees.size else math.nan

    @property
    def nees_mean(self) -> float:
        return float(np.mean(self.nees)) if self.nees.size else math.nan


def consistency(
    estimates: Sequence[Estimate],
    gt: GroundTruth,
    robots: Iterable[str],
    t_start: float,
    rotation: float = 0.0,
) -> dict[str, Consistency]:
    """NEES of every estimate from ``t_start`` on that carries a covariance, per robot, against
    interpolated relative ground truth in the estimate's frame (as in :func:`associate`).
    Methods without covariances (multilateration) get none."""
    out: dict[str, Consistency] = {}
    for robot in robots:
        t, nees = [], []
        for est in estimates:
            if est.t < t_start or robot not in est.positions or robot not in est.covariances:
                continue
            truth = truth_in_frame(est, gt, robot, rotation)
            if truth is None:
                continue
            e = np.subtract(est.positions[robot], truth)
            cov = np.array(est.covariances[robot], float)
            if not np.all(np.isfinite(cov)) or np.linalg.det(cov) <= 0.0:
                continue
            t.append(est.t)
            nees.append(float(e @ np.linalg.solve(cov, e)))
        if t:
            out[robot] = Consistency(np.array(t), np.array(nees))
    return out


def associate_shapes(
    estimates: Sequence[Estimate],
    gt: GroundTruth,
    robots: Iterable[str],
    rotation: float = 0.0,
) -> dict[str, Paired]:
    """Like :func:`associate`, for the published shapes (the formation in its declared gauge,
    :attr:`Estimate.shape`) instead of the positions: align these once for the run
    (:func:`align` ``"run"``), as multilateration's formation is, for the shape APE."""
    shaped = [
        replace(est, positions=dict(est.shape), frame=HEADING_FRAME)
        for est in estimates
        if est.shape
    ]
    return associate(shaped, gt, robots, rotation)


def body_frame_paired(
    estimates: Sequence[Estimate],
    gt: GroundTruth,
    robots: Iterable[str],
    reference_yaws: Iterable[tuple[float, float]],
) -> dict[str, Paired]:
    """Every robot's estimated position in the *reference robot's body frame* (where robot j
    is as the reference would see it: x forward, y left) paired with the same in the truth.

    This is the gauge-free relative position: no shared heading frame, no alignment. The
    estimate's frame turns into the body frame by the reference's heading in it, its odometry
    yaw at the estimate's time (``reference_yaws``: ``(t, yaw)`` in its odometry track's frame,
    :attr:`relloc.localizers.base.Localizer.odometry_yaws`) plus, where the method estimates
    headings, the published heading of the reference's odometry frame (its drift); the truth
    by the reference's motion-capture yaw. Estimates without a recorded yaw are left out.
    """
    yaw_at = dict(reference_yaws)
    out: dict[str, Paired] = {}
    ref = gt.reference
    for robot in robots:
        t, e, g, s = [], [], [], []
        for est in estimates:
            body = est.frame == BODY_FRAME  # already in the body frame
            if robot not in est.positions or (est.t not in yaw_at and not body):
                continue
            truth = gt.relative_at(robot, est.t)
            pose = gt.pose_at(ref, est.t)
            if truth is None or pose is None:
                continue
            heading = (
                0.0
                if body
                else yaw_at[est.t] + (est.headings[ref][0] if ref in est.headings else 0.0)
            )
            t.append(est.t)
            e.append(_to_body(est.positions[robot], heading))
            g.append(_to_body(truth, pose[2]))
            s.append(est.std(robot))
        out[robot] = Paired(
            np.array(t), np.array(e).reshape(-1, 2), np.array(g).reshape(-1, 2), np.array(s)
        )
    return out


def _to_body(v: tuple[float, float], heading: float) -> tuple[float, float]:
    """``v`` turned by ``-heading``: a vector of the frame into the body frame of a robot whose
    heading in that frame is ``heading``."""
    c, s = math.cos(heading), math.sin(heading)
    return (c * v[0] + s * v[1], -s * v[0] + c * v[1])
