"""Evaluation against motion capture: APE, ATE, convergence time.

Definitions follow evo (MichaelGrupp/evo), applied to *relative* positions:

* **APE** of robot ``i`` at an estimate time ``t``: ``|| p_hat_i(t) - (g_i(t) - g_ref(t)) ||``
  where ``g`` is the motion-capture position interpolated at ``t`` (linear, only across gaps
  shorter than ``max_gap``), in the frame the estimate names (the shared heading frame, or the
  reference's body frame: yaw-only in 3D) and of its dimension (the height difference too for
  3D estimates, a Euclidean 3D error). Reported as median, mean, RMSE, std
  and max over the estimates after a warm-up window. The particle filter is never aligned.
* **ATE** of a trajectory: the APE RMSE after aligning the whole estimated relative trajectory
  of one robot to ground truth with one rigid 2-D transform (rotation + translation, Umeyama /
  Kabsch, no scale): it measures the shape of the path, forgiving a constant offset. In 3D
  (a flying team's estimates, z up) the rotation is a yaw about z and the translation 3D.
* **Multilateration** knows the formation only up to rotation and reflection: its fair figure
  uses *one* orthogonal transform (rotation or reflection about the reference) fitted to the
  whole run (``align="run"``); the per-step fit (``align="step"``) is an oracle that uses
  ground truth at every step and is reported as such.
* **Convergence time**: the first estimate time after which at most 5 % of estimates have a
  worst-robot APE above ``threshold`` (0.3 m by default).

Beside these: :mod:`~relloc.evaluation.consistency` (NEES and coverage of the covariances),
:mod:`~relloc.evaluation.gauges` (the published shapes, the reference's body frame) and
:mod:`~relloc.evaluation.selfcal_metrics` (headings, biases).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from relloc.estimate import BODY_FRAME, Estimate
from relloc.events import GroundTruthEvent

FloatArray = NDArray[np.float64]


class GroundTruth:
    """Motion-capture tracks of the robots, interpolated with a bounded gap."""

    def __init__(self, reference: str, max_gap: float = 0.25) -> None:
        self.reference = reference
        self.max_gap = max_gap
        self._t: dict[str, list[float]] = {}
        self._xy: dict[str, list[tuple[float, float, float]]] = {}
        self._z: dict[str, list[float]] = {}
        self._sorted = True

    def add(self, ev: GroundTruthEvent) -> None:
        """Add one motion-capture pose; its height (a position's third entry, where the source
        keeps it) is kept apart, read only for 3D estimates (:meth:`relative_at`); a track
        without heights lies in the ground plane (height 0)."""
        ts = self._t.setdefault(ev.robot, [])
        if ts and ev.t < ts[-1]:
            self._sorted = False
        ts.append(ev.t)
        x, y = ev.position[0], ev.position[1]
        self._xy.setdefault(ev.robot, []).append((x, y, ev.yaw))
        self._z.setdefault(ev.robot, []).append(ev.position[2] if len(ev.position) > 2 else 0.0)

    def _sort(self) -> None:
        if self._sorted:
            return
        for r in self._t:
            order = np.argsort(self._t[r], kind="stable")
            self._t[r] = [self._t[r][i] for i in order]
            self._xy[r] = [self._xy[r][i] for i in order]
            self._z[r] = [self._z[r][i] for i in order]
        self._sorted = True

    @property
    def robots(self) -> list[str]:
        return list(self._t)

    def _bracket(self, robot: str, t: float) -> tuple[int, int, float] | None:
        """The samples ``(a, b)`` around ``t`` and the fraction of the way from ``a`` to ``b``;
        None outside the track or across a gap over ``max_gap``."""
        self._sort()
        ts = self._t.get(robot)
        if not ts or t < ts[0] or t > ts[-1]:
            return None
        i = bisect.bisect_left(ts, t)
        if ts[i] == t:
            return i, i, 0.0
        a, b = i - 1, i
        if ts[b] - ts[a] > self.max_gap:
            return None
        return a, b, (t - ts[a]) / (ts[b] - ts[a])

    def pose_at(self, robot: str, t: float) -> tuple[float, float, float] | None:
        """World pose ``(x, y, yaw)`` at ``t``, or None outside the track or across a long gap."""
        found = self._bracket(robot, t)
        if found is None:
            return None
        a, b, f = found
        if a == b:
            return self._xy[robot][a]
        (xa, ya, wa), (xb, yb, wb) = self._xy[robot][a], self._xy[robot][b]
        return xa + f * (xb - xa), ya + f * (yb - ya), wa + f * math.remainder(wb - wa, math.tau)

    def height_at(self, robot: str, t: float) -> float | None:
        """World height ``z`` at ``t`` (0 for a track without heights), or None as :meth:`pose_at`."""
        found = self._bracket(robot, t)
        if found is None:
            return None
        a, b, f = found
        za, zb = self._z[robot][a], self._z[robot][b]
        return za if a == b else za + f * (zb - za)

    def relative_at(self, robot: str, t: float, dimension: int = 2) -> tuple[float, ...] | None:
        """``g_robot(t) - g_reference(t)`` in the world frame, ``(dx, dy)`` or, for
        ``dimension`` 3, ``(dx, dy, dz)``; None if either is unknown."""
        p, q = self.pose_at(robot, t), self.pose_at(self.reference, t)
        if p is None or q is None:
            return None
        if dimension == 2:
            return p[0] - q[0], p[1] - q[1]
        zp, zq = self.height_at(robot, t), self.height_at(self.reference, t)
        assert zp is not None and zq is not None  # known wherever the pose is
        return p[0] - q[0], p[1] - q[1], zp - zq

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
    """Estimates of one robot associated with ground truth: times, estimates, truths (K, D),
    ``D`` the estimates' dimension (2, or 3 for a flying team)."""

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
    estimate's frame (:func:`truth_in_frame`; ``rotation``: that of its heading frame) and of
    its dimension."""
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
        dim = len(e[0]) if e else 2
        out[robot] = Paired(
            np.array(t), np.array(e).reshape(-1, dim), np.array(g).reshape(-1, dim), np.array(s)
        )
    return out


def truth_in_frame(
    est: Estimate, gt: GroundTruth, robot: str, rotation: float = 0.0
) -> tuple[float, ...] | None:
    """``robot``'s true position relative to the reference at ``est.t`` in the frame the
    estimate is in (:attr:`Estimate.frame`) and of its dimension: the reference's body frame
    (turned by its motion-capture yaw then; in 3D the yaw-only frame, z up, the height
    difference kept), or the heading frame, the world turned by ``rotation`` (rad; the compass
    frame: 0). ``None`` where the truth is unknown."""
    truth = gt.relative_at(robot, est.t, est.dimension)
    if truth is None:
        return None
    if est.frame == BODY_FRAME:
        pose = gt.pose_at(gt.reference, est.t)
        if pose is None:
            return None
        rotation = pose[2]
    if rotation == 0.0:
        return truth
    return _to_body(truth, rotation)


def orthogonal_procrustes(src: FloatArray, dst: FloatArray) -> FloatArray:
    """The orthogonal matrix minimising ``||src R^T - dst||`` of points ``(K, D)``: in 2D any
    rotation or reflection; in 3D one about z (a yaw, or a mirror of x-y), z kept or flipped:
    the robots are level, so z is the team's one axis, but ranges alone never tell up from
    down (with heights measured the flip never fits better)."""
    u, _, vt = np.linalg.svd(dst[:, :2].T @ src[:, :2])
    r = _about_z(u @ vt, src.shape[1])
    if src.shape[1] == 3:
        flipped = r @ np.diag([1.0, 1.0, -1.0])
        if np.sum((src @ flipped.T - dst) ** 2) < np.sum((src @ r.T - dst) ** 2):
            return flipped
    return r


def umeyama_se2(src: FloatArray, dst: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotation R (proper) and translation t minimising ``||src R^T + t - dst||`` of points
    ``(K, D)``: in 3D R is a yaw about z (the x-y fit, z kept) and t is 3D."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    h = (dst - mu_d)[:, :2].T @ (src - mu_s)[:, :2]
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(u @ vt))
    r = _about_z(u @ np.diag([1.0, d]) @ vt, src.shape[1])
    return r, mu_d - r @ mu_s


def _about_z(r2: FloatArray, dimension: int) -> FloatArray:
    """The 2x2 ``r2`` acting on x-y of a ``dimension``-D point (itself in 2D), z kept."""
    if dimension == 2:
        return r2
    r = np.eye(dimension)
    r[:2, :2] = r2
    return r


def align(paired: dict[str, Paired], mode: str) -> dict[str, Paired]:
    """Align estimates about the reference: ``"run"`` one orthogonal map, ``"step"`` one per
    time (:func:`orthogonal_procrustes`: about z only in 3D)."""
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
    """ATE (RMSE) of one robot's relative trajectory after one SE(2) alignment (in 3D a yaw
    about z and a 3D translation: :func:`umeyama_se2`)."""
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


def _to_body(v: Sequence[float], heading: float) -> tuple[float, ...]:
    """``v`` turned by ``-heading``: a vector of the frame into the body frame of a robot whose
    heading in that frame is ``heading`` (a yaw-only turn: a height is carried)."""
    c, s = math.cos(heading), math.sin(heading)
    return (c * v[0] + s * v[1], -s * v[0] + c * v[1], *v[2:])
