"""Cooperative spatial detections (``PF_UV`` / ``PF_ULV``): the detection-association stage.

Robot ``i`` sees an object at ``o_i`` (its body frame), robot ``j`` sees the same object at
``o_j``. With ``R_k`` the rotation by robot ``k``'s heading in the shared heading frame both
point at one place, ``p_i + R_i o_i = p_j + R_j o_j``: the pair measures ``p_j - p_i``.

The derivation: docs/explanation/internals.md, section ``relloc.stages.association``.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict, deque
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.events import (
    DetectionEvent,
    Event,
    ObjectDetection,
    OdometryEvent,
    RangeEvent,
    RelativeObservation,
)
from relloc.odometry import OdometryTrack

FloatArray = NDArray[np.float64]

MAX_ESTIMATE_AGE = 2.0
"""An estimate older than this (s) no longer gates detections (the range gate takes over)."""
CONVERGED_STD = 0.5
"""The estimate of a pair counts as converged (and gates detections) when both robots' position
standard deviations are below this (m): a few times the paper's ``d_th``."""
RANGE_MAX_AGE = 0.3
"""The UWB range the range gate compares with must be at most this old (s): a few range
periods, so that the robots have barely moved since."""
GATE_SIGMAS = 2.0
"""Widening of the estimate gate by the estimate's standard deviation (multiples: about 95 %
of a consistent estimate's errors)."""

REJECTIONS: tuple[str, ...] = (
    "rejected_gate",
    "rejected_inconsistent",
    "rejected_ambiguous",
    "rejected_no_gate",
    "rejected_no_odometry",
)
"""Keys of :attr:`DetectionAssociator.stats` that count rejected pairs (they sum to
``rejected``)."""

_INFEASIBLE = 1e9


@dataclass
class _Frame:
    """The valid objects of one detection frame, body-frame planar positions."""

    t: float
    robot: str
    labels: tuple[str, ...]
    xy: FloatArray  # (K, 2)
    partners: set[str] = field(default_factory=set)
    """Robots this frame has already been paired with."""

    @property
    def distances(self) -> FloatArray:
        return np.hypot(self.xy[:, 0], self.xy[:, 1])


@dataclass(frozen=True)
class _Gate:
    """How one frame pair is gated: its mode and, per mode, what candidates are compared to."""

    mode: Literal["estimate", "range", "none"]
    predicted: tuple[float, float] = (math.nan, math.nan)
    """Estimated ``p_j - p_i`` at the observation time (estimate mode)."""
    distance: float = math.nan
    """Bias-corrected UWB range (range mode)."""
    threshold: float = math.nan


class DetectionAssociator:
    """Pairs two robots' detections of one object into relative-position observations.

    A pipeline stage (see :class:`relloc.engine.Stage`): :meth:`process` every event in time
    order, :meth:`feedback` every estimate of the localizer behind it. See the module docstring
    for the method and the counters in :attr:`stats`.
    """

    def __init__(self, config: TeamConfig) -> None:
        self.config = config
        fc, ac = config.filter, config.association
        self.window = ac.detection_window
        self.d_th = ac.d_th
        self.sigma_det = ac.sigma_det
        self.sigma_per_m = ac.det_sigma_per_m
        self.range_gate = ac.det_range_gate
        self.heading_drift = ac.det_heading_drift
        for name in ("detection_window", "d_th", "sigma_det", "det_range_gate"):
            value = getattr(ac, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"association.{name} must be positive, got {value!r}")
        if fc.self_calibration.heading_mode != "compass":
            raise ValueError(
                "cooperative detections need each robot's heading in the shared frame "
                "(filter.self_calibration.heading_mode = 'compass'); with heading_mode = "
                f"{fc.self_calibration.heading_mode!r} the headings are only known inside the filter"
            )
        online_scale = (
            fc.self_calibration.odom_scale_mode == "online"
        )  # then the config's scale is not read
        self.tracks: dict[str, OdometryTrack] = {
            r.name: OdometryTrack(
                r.heading_offset, 1.0 if online_scale else r.odom_scale, r.odom_mode
            )
            for r in config.robots
        }
        self.stats: Counter[str] = Counter({"proposed": 0, "accepted": 0, "rejected": 0})
        self.estimate: Estimate | None = None
        self._frames: dict[str, deque[_Frame]] = {r: deque() for r in config.robot_names}
        self._ranges: dict[frozenset[str], tuple[float, float]] = {}  # pair -> (t, true distance)
        self._last_odometry: dict[str, OdometryEvent] = {}
        self._moving_time: defaultdict[str, float] = defaultdict(float)  # seconds in motion

    # ------------------------------------------------------------------ stage API
    def process(self, event: Event) -> list[Event]:
        """Pass ``event`` through, followed by the observations it completed (often none)."""
        if isinstance(event, OdometryEvent):
            self._add_odometry(event)
        elif isinstance(event, RangeEvent):
            self._add_range(event)
        elif isinstance(event, DetectionEvent):
            return [event, *self._add_detections(event)]
        return [event]

    def feedback(self, estimate: Estimate) -> None:
        """Remember the localizer's latest estimate: it gates detections once converged."""
        if self.estimate is None or estimate.t >= self.estimate.t:
            self.estimate = estimate

    # ------------------------------------------------------------------ inputs
    def _add_odometry(self, ev: OdometryEvent) -> None:
        track = self.tracks.get(ev.robot)
        values = (ev.t, ev.x, ev.y, ev.yaw, ev.v, ev.w)
        if track is None or not all(map(math.isfinite, values)) or ev.t <= track.last_time:
            return  # the localizer rejects and counts these; the stage just does not use them
        track.add(ev)
        previous = self._last_odometry.get(ev.robot)
        if previous is not None and _moved(previous, ev):
            self._moving_time[ev.robot] += ev.t - previous.t
        self._last_odometry[ev.robot] = ev

    def _add_range(self, ev: RangeEvent) -> None:
        if ev.robot_a not in self.tracks or ev.robot_b not in self.tracks:
            return
        if ev.robot_a == ev.robot_b or not (math.isfinite(ev.distance) and ev.distance > 0.0):
            return
        if ev.corrected:
            distance = ev.distance
        else:
            bias, scale, _ = self.config.uwb.calibration(*self.config.range_nodes(ev))
            distance = (ev.distance - bias) / scale
        key = frozenset((ev.robot_a, ev.robot_b))
        previous = self._ranges.get(key)
        if previous is None or ev.t >= previous[0]:
            self._ranges[key] = (ev.t, distance)

    def _add_detections(self, ev: DetectionEvent) -> list[Event]:
        if ev.robot not in self._frames:
            self.stats["unknown_robot"] += 1
            return []
        self.stats["frames"] += 1
        labels, points = [], []
        for obj in ev.objects:
            if not _valid(obj):
                self.stats["invalid_object"] += 1
                continue
            labels.append(obj.label)
            points.append((obj.x, obj.y))
        self.stats["objects"] += len(points)
        if not points or not math.isfinite(ev.t):
            return []
        frame = _Frame(ev.t, ev.robot, tuple(labels), np.array(points, dtype=float))
        out: list[Event] = []
        for other, frames in self._frames.items():
            if other == ev.robot:
                continue
            self._forget(frames, ev.t)
            partner = self._partner(frames, frame)
            if partner is not None:
                partner.partners.add(ev.robot)
                frame.partners.add(other)
                out += self._associate(partner, frame)
        own = self._frames[ev.robot]
        self._forget(own, ev.t)
        own.append(frame)
        return out

    def _forget(self, frames: deque[_Frame], now: float) -> None:
        """Drop frames too old to pair with anything captured from ``now`` on."""
        while frames and frames[0].t < now - 2.0 * self.window:
            frames.popleft()

    def _partner(self, frames: deque[_Frame], frame: _Frame) -> _Frame | None:
        """The nearest frame in time within the window not yet paired with ``frame.robot``."""
        best, best_dt = None, math.inf
        for f in frames:
            dt = abs(f.t - frame.t)
            if dt <= self.window + 1e-9 and frame.robot not in f.partners and dt < best_dt:
                best, best_dt = f, dt
        return best

    # ------------------------------------------------------------------ association
    def _associate(self, a: _Frame, b: _Frame) -> list[Event]:
        """Accepted pairs between frame ``a`` (observer) and ``b`` (target) as observations."""
        compatible = np.array(
            [[la == lb or not la or not lb for lb in b.labels] for la in a.labels], dtype=bool
        )
        n_proposed = int(compatible.sum())
        if n_proposed == 0:
            return []
        self.stats["proposed"] += n_proposed
        i, j = a.robot, b.robot
        t = max(a.t, b.t)
        if self.tracks[i].empty or self.tracks[j].empty:
            return self._reject(n_proposed, "rejected_no_odometry")
        # Each side's objects in the shared heading frame, relative to the robot at time t:
        # R_k o_k carried by the robot's own odometry motion between its capture and t.
        world_a = self._to_shared(a, t)
        world_b = self._to_shared(b, t)
        vectors = world_a[:, None, :] - world_b[None, :, :]  # (Ka, Kb, 2): p_j - p_i
        d_a, d_b = a.distances, b.distances
        sigma = self._sigma(i, d_a)[:, None] + self._sigma(j, d_b)[None, :]
        sigma = np.sqrt(self.sigma_det**2 + sigma)
        gate = self._gate(i, j, t)
        if gate.mode == "none":
            return self._reject(n_proposed, "rejected_no_gate")
        if gate.mode == "estimate":
            residual = np.hypot(
                vectors[..., 0] - gate.predicted[0], vectors[..., 1] - gate.predicted[1]
            )
        else:
            residual = np.abs(np.hypot(vectors[..., 0], vectors[..., 1]) - gate.distance)
        feasible = compatible & (residual < gate.threshold)
        n_feasible = int(feasible.sum())
        if n_feasible < n_proposed:
            self._reject(n_proposed - n_feasible, "rejected_gate")
        if n_feasible == 0:
            return []
        matching, ambiguous = _consensus(vectors, sigma, residual, feasible)
        if ambiguous:
            return self._reject(n_feasible, "rejected_ambiguous")
        if n_feasible > len(matching):
            self._reject(n_feasible - len(matching), "rejected_inconsistent")
        self.stats["accepted"] += len(matching)
        self.stats[f"accepted_by_{gate.mode}"] += len(matching)
        return [
            RelativeObservation(
                t,
                observer=i,
                target=j,
                vector=(float(vectors[m, n, 0]), float(vectors[m, n, 1])),
                sigma=float(sigma[m, n]),
            )
            for m, n in matching
        ]

    def _sigma(self, robot: str, d: FloatArray) -> FloatArray:
        """One side's variance (per axis) of ``R o`` for detections at distances ``d``.

        Depth noise and a fixed heading error grow with distance (``det_sigma_per_m``); the
        heading of odometry also drifts while the robot moves (``det_heading_drift`` rad per
        second of motion), which displaces the object sideways by ``d * heading error``: a
        variance ``(d psi)^2`` in one unknown direction, half of it per axis.
        """
        psi = self.heading_drift * self._moving_time[robot]
        return (self.sigma_per_m**2 + 0.5 * psi**2) * d**2

    def _reject(self, n: int, reason: str) -> list[Event]:
        self.stats["rejected"] += n
        self.stats[reason] += n
        return []

    def _to_shared(self, frame: _Frame, t: float) -> FloatArray:
        """``R_k o + (p_k(t_frame) - p_k(t))`` for each object: the object seen from the robot's
        position at ``t``, in the shared heading frame."""
        track = self.tracks[frame.robot]
        x0, y0, yaw, _ = track.pose_at(frame.t)
        x1, y1, _, _ = track.pose_at(t)
        c, s = math.cos(yaw), math.sin(yaw)
        ox, oy = frame.xy[:, 0], frame.xy[:, 1]
        return np.column_stack([c * ox - s * oy + (x0 - x1), s * ox + c * oy + (y0 - y1)])

    def _gate(self, i: str, j: str, t: float) -> _Gate:
        """The estimate gate if the estimate of the pair has converged, else the range gate."""
        est = self.estimate
        if est is not None and t - est.t <= MAX_ESTIMATE_AGE:
            std_i, std_j = (0.0 if r == est.reference else est.std(r) for r in (i, j))
            if max(std_i, std_j) < CONVERGED_STD:  # NaN (unknown robot) compares False
                p_i = self._position(est, i, t)
                p_j = self._position(est, j, t)
                return _Gate(
                    "estimate",
                    predicted=(p_j[0] - p_i[0], p_j[1] - p_i[1]),
                    threshold=self.d_th + GATE_SIGMAS * math.hypot(std_i, std_j),
                )
        latest = self._ranges.get(frozenset((i, j)))
        if latest is not None and abs(t - latest[0]) <= RANGE_MAX_AGE:
            return _Gate("range", distance=latest[1], threshold=self.range_gate)
        return _Gate("none")

    def _position(self, est: Estimate, robot: str, t: float) -> tuple[float, float]:
        """Estimated position of ``robot`` relative to the reference frame origin at ``est.t``,
        carried to ``t`` with the robot's odometry (the reference's own motion is subtracted
        by the caller taking differences: both sides use the same estimate)."""
        x, y = (0.0, 0.0) if robot == est.reference else est.positions[robot]
        track = self.tracks[robot]
        if track.empty:
            return x, y
        x0, y0, _, _ = track.pose_at(est.t)
        x1, y1, _, _ = track.pose_at(t)
        return x + (x1 - x0), y + (y1 - y0)


def _moved(before: OdometryEvent, after: OdometryEvent) -> bool:
    """Whether a robot moved between two odometry messages (twist or pose changed)."""
    if abs(after.v) > 1e-3 or abs(after.w) > 1e-3:
        return True
    turned = abs(math.remainder(after.yaw - before.yaw, math.tau))
    return math.hypot(after.x - before.x, after.y - before.y) > 1e-4 or turned > 1e-4


def _valid(obj: ObjectDetection) -> bool:
    """A usable detection: finite planar position, not the all-zero 'no depth' marker."""
    if not (math.isfinite(obj.x) and math.isfinite(obj.y)):
        return False
    return not (obj.x == 0.0 and obj.y == 0.0 and obj.z == 0.0)


def _consensus(
    vectors: FloatArray, sigma: FloatArray, residual: FloatArray, feasible: NDArray[np.bool_]
) -> tuple[list[tuple[int, int]], bool]:
    """The largest one-to-one set of feasible pairs implying one common vector.

    Each feasible pair is a hypothesis for ``p_j - p_i``; the pairs consistent with it (their
    vectors within ``2 * hypot(sigma, sigma')``) are matched one-to-one by the Hungarian
    algorithm on the disagreement. Returns the best matching (most pairs, then smallest total
    gate residual) and whether an equally large matching implies an inconsistent vector.
    """
    cands = list(zip(*np.nonzero(feasible), strict=True))
    results: list[tuple[int, float, FloatArray, list[tuple[int, int]]]] = []
    for m0, n0 in cands:
        v0, s0 = vectors[m0, n0], sigma[m0, n0]
        disagreement = np.hypot(vectors[..., 0] - v0[0], vectors[..., 1] - v0[1])
        consistent = feasible & (disagreement <= 2.0 * np.hypot(sigma, s0))
        cost = np.where(consistent, disagreement, _INFEASIBLE)
        rows, cols = linear_sum_assignment(cost)
        matching = [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if consistent[r, c]]
        total = float(sum(residual[r, c] for r, c in matching))
        mean = np.mean([vectors[r, c] for r, c in matching], axis=0)
        results.append((len(matching), total, mean, matching))
    results.sort(key=lambda r: (-r[0], r[1]))
    size, _, mean, best = results[0]
    best_sigma = max(float(sigma[r, c]) for r, c in best)
    for other_size, _, other_mean, _ in results[1:]:
        if other_size < size:
            break
        if np.hypot(*(other_mean - mean)) > 2.0 * math.sqrt(2.0) * best_sigma:
            return best, True
    return best, False
