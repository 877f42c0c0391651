"""What every localizer shares: validation, the batching grid, odometry tracks, emission.

Sensors are asynchronous: each robot's odometry, each UWB pair and each camera arrive at their
own rates and lags. A localizer

* validates every event (non-finite values, negative ranges, unknown robots, time going
  backwards): a bad event is **rejected and counted** in :attr:`Localizer.stats` (and logged),
  never allowed to crash the engine or to corrupt the estimate. The time checks are here; the
  measurement's own rule is its model's (:mod:`relloc.filter.registry`);
* keeps each robot's odometry in an :class:`~relloc.odometry.OdometryTrack` (shared heading
  frame), so that it can predict to any instant;
* gathers the measurements stamped within one cell of a fixed ``update_period`` grid into one
  batch, predicts with every robot's odometry up to the batch time (its newest stamp), and
  fuses the batch in one update (the stacked measurement vector of the paper). A grid, not a
  window opened by the first measurement: a pair ranging at the update rate with some jitter
  then gives one range per batch, not now one, now two;
* emits an :class:`~relloc.estimate.Estimate` (each robot's position relative to the
  reference, with covariance) at ``estimate_period``.

Subclasses differ only in ``_step``, the fusion of one batch. :class:`FilterLocalizer` is that
step for a filter of :mod:`relloc.filter.base`: predict, update with the batch's measurement
models, estimate, maybe resample.
"""

from __future__ import annotations

import logging
import math
from collections import Counter, deque
from typing import Any

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.events import DetectionEvent, Event, GroundTruthEvent, OdometryEvent
from relloc.filter.base import FilterEstimate, WeightedFilter
from relloc.filter.measurement import MeasurementModel, ModelContext, finite
from relloc.filter.motion import OdometryMotion
from relloc.filter.registry import MODELS, model_for
from relloc.filter.state import StateLayout, TeamLayout
from relloc.filter.summary import estimate_fields
from relloc.odometry import OdometryTrack

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
Measurement = Any
"""An event some registered measurement model consumes."""

_TIME_TOLERANCE = 1e-9
_JUMP_VOTES = 3
"""Events in a row that must agree on a time far ahead before the clock follows them."""

_YAW_LOG = 200_000
"""Odometry yaws kept per robot for evaluating estimated headings: 5.5 h at 10 Hz."""


class Localizer:
    """Validation, odometry tracks and measurement batching common to every method."""

    method = "base"

    def __init__(self, config: TeamConfig, layout: StateLayout | None = None) -> None:
        self.config = config
        self._layout = layout or StateLayout(config.robot_names, config.reference)
        fc = config.filter
        self.update_period = fc.update_period
        self.estimate_period = fc.estimate_period
        self.tracks = {
            r.name: OdometryTrack(
                *self._track_frame(r.name), r.odom_mode, max_extrapolation=fc.odometry.max_odom_extrapolation
            )
            for r in config.robots
        }
        self.first_odometry: dict[str, tuple[float, float]] = {}
        """Per robot, ``(t, yaw)`` of its first odometry sample (in its track's frame)."""
        self.odometry_yaws: dict[str, deque[tuple[float, float]]] = {}
        """Each robot's odometry yaw at every estimate time where headings are estimated, and the
        reference robot's always (for evaluating the published headings and the body-frame
        positions; the filter does not use it). Bounded, for live runs."""
        self.stats: Counter[str] = Counter()
        self.last_estimate: Estimate | None = None
        self._memory: dict[type, dict[Any, Any]] = {}
        self._pending: list[Measurement] = []
        self._batch_start = math.nan
        self._closed_until = -math.inf  # measurements older than this come too late
        self._last_emit = -math.inf
        self._clock = -math.inf  # newest accepted stamp
        self._jump_candidate = math.nan  # stamp of the last event rejected as a time jump
        self._jump_votes = 0  # consecutive rejected events that agree with it

    @property
    def layout(self) -> TeamLayout:
        """The team's layout: robot order, and which node pairs' biases are estimated."""
        return self._layout

    def _track_frame(self, robot: str) -> tuple[float, float]:
        """Heading offset and odometry scale that robot's track applies: the config's, unless
        the filter estimates them (the self-calibrating localizer)."""
        r = self.config.robot(robot)
        return r.heading_offset, r.odom_scale

    # ---------------------------------------------------------------- public API
    def process(self, event: Event) -> list[Estimate]:
        """Consume one event; returns the estimates that became due (often none)."""
        model = model_for(event)
        reason = self._rejection(event, model)
        if reason is not None:
            self._reject(reason, event)
            return []
        if isinstance(event, OdometryEvent):
            self._clock = max(self._clock, event.t)
            track = self.tracks[event.robot]
            first = track.empty
            track.add(event)
            if first:
                self.first_odometry[event.robot] = (event.t, track.pose_at(event.t)[2])
            self.stats["odometry"] += 1
            return self._advance(event.t)
        if model is not None:
            self._clock = max(self._clock, event.t)
            out: list[Estimate] = []
            if self._pending and self._cell(event.t) > self._cell(self._batch_start):
                out += self._run_batch()
            if not self._pending:
                self._batch_start = event.t
            self._pending.append(event)
            self.stats[model.stat] += 1
            return out
        self.stats["ignored_" + type(event).__name__] += 1
        return []

    def flush(self) -> list[Estimate]:
        """Fuse what is still pending (end of a recording)."""
        return self._run_batch() if self._pending else []

    # ---------------------------------------------------------------- validation
    def _rejection(self, event: Event, model: type[MeasurementModel] | None) -> str | None:
        if isinstance(event, GroundTruthEvent | DetectionEvent):
            return None
        if model is None and not isinstance(event, OdometryEvent):
            return "unknown_event_type"
        if not finite(event.t):
            return "invalid_time"
        if self._time_jump(event.t):
            return "time_jump"
        if model is not None:
            return model.rejection(event, self)
        if event.robot not in self.layout.robots:
            return "unknown_robot"
        if not all(map(finite, (event.x, event.y, event.yaw, event.v, event.w))):
            return "invalid_odometry"
        if event.t <= self.tracks[event.robot].last_time + _TIME_TOLERANCE:
            return "out_of_order_odometry"
        return None

    def is_late(self, t: float) -> bool:
        """Whether a measurement stamped ``t`` is older than the filter's time (it can no
        longer be fused)."""
        return t < self._closed_until

    def memory(self, model: type) -> dict[Any, Any]:
        """A dictionary of ``model``'s validation rule (e.g. each pair's last range)."""
        return self._memory.setdefault(model, {})

    def _cell(self, t: float) -> int:
        """Index of the batching grid cell that holds time ``t``."""
        return math.floor(t / self.update_period)

    def _time_jump(self, t: float) -> bool:
        """Whether ``t`` jumps ahead of the clock by more than ``max_time_jump`` without
        ``_JUMP_VOTES`` events in a row agreeing on the new time (see
        :class:`relloc.config.FilterConfig`)."""
        limit = self.config.filter.max_time_jump
        if self._clock == -math.inf or t <= self._clock + limit:
            return False  # the first event sets the clock
        agrees = abs(t - self._jump_candidate) <= limit
        self._jump_votes = self._jump_votes + 1 if agrees else 1
        self._jump_candidate = t
        if self._jump_votes < _JUMP_VOTES:
            return True
        self._jump_votes, self._jump_candidate = 0, math.nan
        return False

    def _reject(self, reason: str, event: Event) -> None:
        self.stats["rejected_" + reason] += 1
        n = self.stats["rejected_" + reason]
        if n == 1 or n % 1000 == 0:
            log.warning("rejected %s (%s, %d so far): %r", type(event).__name__, reason, n, event)

    @property
    def rejected(self) -> dict[str, int]:
        return {k.removeprefix("rejected_"): v for k, v in self.stats.items() if k.startswith("rejected_")}

    # ---------------------------------------------------------------- batching
    def _advance(self, now: float) -> list[Estimate]:
        """Odometry moved the clock: fuse a batch that is complete by now."""
        if self._pending and now >= (self._cell(self._batch_start) + 2) * self.update_period:
            return self._run_batch()
        return []

    def _run_batch(self) -> list[Estimate]:
        batch, self._pending = self._pending, []
        t = max(m.t for m in batch)
        # The filter is now at t: a measurement stamped before it can no longer be fused.
        self._closed_until = max(self._closed_until, t)
        est = self._step(t, batch)
        if est is None:
            return []
        # A batch is stamped with its newest measurement, so batch times jitter within a window:
        # half a window of tolerance keeps one estimate per estimate_period.
        if est.t - self._last_emit >= self.estimate_period - 0.5 * self.update_period:
            self._last_emit = est.t
            return [est]
        return []

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        raise NotImplementedError

    # ---------------------------------------------------------------- emission
    def _emit(self, t: float, fe: FilterEstimate) -> Estimate:
        """The :class:`Estimate` of a filter's moments at ``t`` (and, where it estimates
        headings, each robot's odometry yaw then, for evaluating them)."""
        positions, covs = {}, {}
        for k, robot in enumerate(self.layout.others):
            positions[robot] = (float(fe.mean[k, 0]), float(fe.mean[k, 1]))
            c = fe.cov[k]
            covs[robot] = ((float(c[0, 0]), float(c[0, 1])), (float(c[1, 0]), float(c[1, 1])))
        for robot in {*fe.headings, self.layout.reference}:  # the reference's: body-frame evaluation
            if not self.tracks[robot].empty:
                yaws = self.odometry_yaws.setdefault(robot, deque(maxlen=_YAW_LOG))
                yaws.append((t, self.tracks[robot].pose_at(t)[2]))
        honest = {} if fe.summary is None else estimate_fields(fe.summary, self.layout.reference, self.layout.others)
        est = Estimate(
            t, self.method, self.layout.reference, positions, covs, fe.ess, fe.headings, fe.biases, fe.scales,
            **honest,
        )
        self.last_estimate = est
        return est


class FilterLocalizer(Localizer):
    """A localizer around a filter of :mod:`relloc.filter.base`: after its start (subclasses'
    ``_start``, once ``init_window`` of measurements has been gathered) every batch is
    predicted to, fused through its measurement models, and estimated."""

    filter: WeightedFilter
    range_model = "nlos"
    """Which range likelihood (:class:`relloc.filter.measurement.ModelContext`) the filter uses."""

    def __init__(self, config: TeamConfig, layout: StateLayout | None = None, *, seed: int = 0) -> None:
        super().__init__(config, layout)
        fc = config.filter
        self.rng = np.random.default_rng(seed)
        self.motion = OdometryMotion(fc.odometry.process_noise, fc.odometry.odom_noise_per_m, fc.odometry.odom_noise_per_rad)
        self.initialized = False
        self.t = math.nan
        self._anchor: dict[str, tuple[float, float, float]] = {}
        self._init_batch: list[Measurement] = []

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        if not self.initialized:
            self._init_batch += batch
            first = min(m.t for m in self._init_batch)
            if t - first < self.config.filter.init_window:
                return None
            start, self._init_batch = self._init_batch, []
            return self._start(t, start)
        self.filter.predict(*self._motion_to(t))
        models = self.models(batch, self.filter)
        if not self.filter.update(models):
            self.stats["update_no_support"] += 1
        est = self._emit(t, self.filter.estimate())
        if self.filter.maybe_resample():
            self.stats["resampled"] += 1
        for name, count in self.filter.counters().items():
            self.stats[name] = count
        return est

    def _start(self, t: float, batch: list[Measurement]) -> Estimate | None:
        raise NotImplementedError

    def _started(self, t: float) -> None:
        """The start is done at ``t``: odometry from now on moves the filter."""
        self.initialized = True
        self.t = t
        self._anchor = {r: self._odometry_pose(r, t) for r in self.layout.robots}

    # ---------------------------------------------------------------- models
    def models(
        self, batch: list[Measurement], target: WeightedFilter, *, robust: bool = True, count: bool = True
    ) -> list[MeasurementModel]:
        """The measurement models of ``batch`` for ``target``'s state layout, in registry
        order. Measurements in the shared heading frame are left out (and counted, with
        ``count``) where the localizer's filter has no such frame."""
        groups: dict[type, list[Measurement]] = {}
        for m in batch:
            cls = model_for(m)
            if cls is not None:
                groups.setdefault(cls, []).append(m)
        yaws = {r: self._odometry_pose(r, max(m.t for m in batch))[2] for r in self.layout.robots} if batch else None
        context = ModelContext(
            self.config, target.layout, robust, self.range_model, yaws, self.filter.shared_heading
        )
        out: list[MeasurementModel] = []
        for cls in dict.fromkeys(MODELS.values()):
            events = groups.get(cls)
            if not events:
                continue
            if cls.needs_shared_heading and not self.filter.shared_heading:
                if count:
                    self.stats[f"ignored_{cls.stat}_no_shared_heading"] += len(events)
                continue
            out += cls.build(events, context)
        return out

    # ---------------------------------------------------------------- prediction
    def _odometry_pose(self, robot: str, t: float) -> tuple[float, float, float]:
        track = self.tracks[robot]
        if track.empty:
            return (math.nan, math.nan, math.nan)
        x, y, yaw, _ = track.pose_at(t)
        return (x, y, yaw)

    def _motion_to(self, t: float) -> tuple[FloatArray, FloatArray, float]:
        """Every robot's odometry displacement ``(N, 2)`` and its noise ``(N,)`` since the last
        step, and the time step; the filter is at ``t`` after it."""
        n = len(self.layout.robots)
        disp = np.zeros((n, 2))
        sigma = np.zeros(n)
        for i, robot in enumerate(self.layout.robots):
            now = self._odometry_pose(robot, t)
            before = self._anchor.get(robot, (math.nan,) * 3)
            if math.isnan(now[0]):
                continue
            if math.isnan(before[0]):
                before = now  # odometry started since the last step: no known motion yet
            disp[i] = (now[0] - before[0], now[1] - before[1])
            dist = math.hypot(*disp[i])
            turn = abs(math.remainder(now[2] - before[2], math.tau))
            sigma[i] = self.motion.step_sigma(dist, turn)
            self._anchor[robot] = now
        dt = max(t - self.t, 0.0)
        self.t = t
        return disp, sigma, dt
