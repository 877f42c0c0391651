"""What every localizer shares: validation, the team clock, the batching grid, odometry tracks.

Sensors are asynchronous: each robot's odometry, each UWB pair and each camera arrive at their
own rates and lags. A :class:`Localizer`

* validates every event (non-finite values, negative ranges, unknown robots, time going
  backwards): a bad event is **rejected and counted** in :attr:`Localizer.stats` (and logged),
  never allowed to crash the engine or to corrupt the estimate. The time checks are here; the
  measurement's own rule is its model's (:mod:`relloc.filter.registry`);
* keeps a **team clock** that no single stamp can capture (:mod:`~relloc.localizers.clock`):
  the first events set it by their median stamp, a stamp far off it is rejected and votes for
  a jump, and a step of the whole stream is followed (``clock_jumps_followed``; the times the
  localizer holds move with it);
* keeps each robot's odometry in a track (:mod:`~relloc.localizers.tracks`), so that it can
  predict to any instant; a reset or jump re-anchors the track (``odometry_reanchored``);
* gathers the measurements of one cell of the ``UPDATE_PERIOD`` grid into one batch
  (:mod:`~relloc.localizers.grid`, which also gives the live wake rule), and fuses it at the
  batch time (its newest stamp) in one step: subclasses differ only in ``_step``;
* emits at most one estimate per ``ESTIMATE_PERIOD``.

:class:`~relloc.localizers.stepped.SteppedLocalizer` is that step for an estimator kind
(:mod:`relloc.estimators`), :class:`~relloc.localizers.filtered.FilterLocalizer` for a weighted
filter of :mod:`relloc.filter.base`.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.events import (
    DetectionEvent,
    Event,
    GroundTruthEvent,
    HeightEvent,
    OdometryEvent,
    WakeRule,
)
from relloc.filter.measurement import MeasurementModel, finite
from relloc.filter.registry import model_for
from relloc.filter.state import StateLayout, TeamLayout
from relloc.localizers.clock import TeamClock
from relloc.localizers.grid import UPDATE_PERIOD, BatchGrid
from relloc.localizers.tracks import OdometryTracks
from relloc.odometry import OdometryTrack

log = logging.getLogger(__name__)

Measurement = Any
"""An event some registered measurement model consumes."""
ESTIMATE_PERIOD = 0.1
"""Estimates are emitted at this period (s), the grid's."""

_UNFUSED = (GroundTruthEvent, DetectionEvent, HeightEvent)
"""Events of the vocabulary no localizer fuses through a measurement model: ground truth (for
evaluation), raw detections (the association stage's input), heights (a 3D estimator takes
them itself; a 2D one has no height). Ignored and counted, never rejected."""


class Localizer:
    """Validation, the team clock, odometry tracks and measurement batching of every method.

    :attr:`step_timer`, when set, is called after each step (each batch fused) with the batch
    time, the seconds the step took on :attr:`step_clock` (``time.perf_counter`` unless set) and
    the estimate it built (``None``: none): how a benchmark times the filter step. Unset (the
    default), nothing is timed.
    """

    method = "base"

    def __init__(self, config: TeamConfig, layout: StateLayout | None = None) -> None:
        self.config = config
        self._layout = layout or StateLayout(config.robot_names, config.reference)
        self.update_period = UPDATE_PERIOD
        self.estimate_period = ESTIMATE_PERIOD
        self.shape_wanted = True
        """Whether the estimates' consumers read their shape and distances (a live server sets
        it from whether anyone subscribes to its shape key); False leaves them out, uncomputed."""
        self.keeps_run = True
        """Whether a localizer that can smooth the whole run afterwards keeps what that needs
        (a live server sets it False: its memory stays bounded)."""
        self.stats: Counter[str] = Counter()
        self.last_estimate: Estimate | None = None
        self.clock = TeamClock()
        self.grid = BatchGrid(UPDATE_PERIOD)
        self.odometry = OdometryTracks(config, self._track_frame)
        self._memory: dict[type, dict[Any, Any]] = {}
        self._last_emit = -math.inf
        self._batching = False
        self.step_timer: Callable[[float, float, Estimate | None], None] | None = None
        """Called after each step with its batch time, its duration (s) and its estimate."""
        self.step_clock: Callable[[], float] = time.perf_counter
        """The clock :attr:`step_timer`'s durations are read on (e.g. ``time.thread_time``)."""

    @property
    def layout(self) -> TeamLayout:
        """The team's layout: robot order, and which node pairs' biases are estimated."""
        return self._layout

    @property
    def tracks(self) -> dict[str, OdometryTrack]:
        return self.odometry.tracks

    @property
    def first_odometry(self) -> dict[str, tuple[float, float]]:
        """Per robot, ``(t, yaw)`` of its first odometry sample (in its track's frame)."""
        return self.odometry.first

    @property
    def odometry_yaws(self) -> dict[str, deque[tuple[float, float]]]:
        """Each robot's odometry yaw at every estimate time where headings are estimated, and the
        reference robot's always (for evaluating the published headings and the body-frame
        positions; the filter does not use it). Bounded, for live runs."""
        return self.odometry.yaws

    @property
    def odometry_faults(self) -> dict[str, int]:
        """Per robot, how many odometry resets or jumps re-anchored its track."""
        return self.odometry.faults

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
        if model is None and not isinstance(event, OdometryEvent):
            self.stats["ignored_" + type(event).__name__] += 1
            return []
        if not self.clock.started:
            # The first events cannot set the clock alone (relloc.localizers.clock).
            return [est for ev in self.clock.warm(event) for est in self._timed(ev, model_for(ev))]
        return self._timed(event, model)

    def wake_rule(self) -> WakeRule:
        """Which events could make this localizer fuse a batch now (and so emit an estimate):
        what a live server must process at once; any other event can wait and be processed
        later, in its order, with the same result (:meth:`BatchGrid.wake_rule`)."""
        return self.grid.wake_rule(self.clock.now, self.clock.limit)

    def flush(self) -> list[Estimate]:
        """Fuse what is still pending (end of a recording)."""
        out = [est for ev in self.clock.end_warmup() for est in self._timed(ev, model_for(ev))]
        return out + (self._run_batch() if self.grid.pending else [])

    # ---------------------------------------------------------------- time, then the grid
    def _timed(self, event: Event, model: type[MeasurementModel] | None) -> list[Estimate]:
        """An event past the checks of its own: the team clock's check, then into the filter."""
        out: list[Estimate] = []
        reason = self.clock.check(event, self._unusable)
        if reason == "follow":
            out += self._follow_jump(event.t - self.clock.now)
        elif reason is not None:
            self._reject(reason, event)
            return []
        return out + self._accept(event, model)

    def _accept(self, event: Event, model: type[MeasurementModel] | None) -> list[Estimate]:
        self.clock.accepted(event)
        if isinstance(event, OdometryEvent):
            if self.odometry.stale(event):
                self._reject("out_of_order_odometry", event)
                return []
            self.clock.advance(event.t)
            if self.odometry.add(event):
                self.stats["odometry_reanchored"] += 1
            self.stats["odometry"] += 1
            return self._run_batch() if self.grid.due(event.t) else []
        assert model is not None
        self.clock.advance(event.t)
        out: list[Estimate] = []
        if self.grid.closed_by(event.t):
            if self.grid.full:
                self.stats["batches_forced"] += 1
            out += self._run_batch()
        self.grid.add(event)
        self.stats[model.stat] += 1
        return out

    def _unusable(self, event: Event) -> bool:
        if isinstance(event, OdometryEvent):
            return self.odometry.stale(event)
        return self.is_late(event.t)

    def _follow_jump(self, dt: float) -> list[Estimate]:
        """The whole stream's clock stepped by ``dt``: fuse what is pending, then move the
        times the localizer holds by ``dt`` (the clock, the fused horizon, the last emission,
        the tracks' history backwards), so that the next batch predicts over the step's real
        length, not over the step."""
        out = self._run_batch() if self.grid.pending else []
        log.warning("the team's clock stepped by %+.3f s: followed", dt)
        self.stats["clock_jumps_followed"] += 1
        self.clock.follow(dt)
        self.grid.closed_until += dt
        self._last_emit += dt
        self.odometry.follow(dt)
        self._shift_time(dt)
        return out

    def _shift_time(self, dt: float) -> None:
        """A subclass's own times moved by ``dt`` (a followed clock jump)."""

    def _run_batch(self) -> list[Estimate]:
        t, batch = self.grid.take()
        self._batching = True
        try:
            if self.step_timer is None:
                est = self._step(t, batch)
            else:
                start = self.step_clock()
                est = self._step(t, batch)
                self.step_timer(t, self.step_clock() - start, est)
        finally:
            self._batching = False
        if est is None:
            return []
        if self._due(est.t):
            self._last_emit = est.t
            return [est]
        return []

    def _due(self, t: float) -> bool:
        """Whether an estimate stamped ``t`` would be emitted. A batch is stamped with its
        newest measurement, so batch times jitter within a window: half a window of tolerance
        keeps one estimate per estimate_period."""
        return t - self._last_emit >= self.estimate_period - 0.5 * self.update_period

    def publishes(self, t: float) -> bool:
        """Whether an estimate stamped ``t`` built now is emitted: False only within a batch's
        step for an estimate that comes too soon after the last one (what only a published
        estimate carries may then be skipped); True anywhere else."""
        return not self._batching or self._due(t)

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        raise NotImplementedError

    # ---------------------------------------------------------------- validation
    def _rejection(self, event: Event, model: type[MeasurementModel] | None) -> str | None:
        if isinstance(event, _UNFUSED):
            return None
        if model is None and not isinstance(event, OdometryEvent):
            return "unknown_event_type"
        if not finite(event.t):
            return "invalid_time"
        if model is not None:
            return model.rejection(event, self)
        assert isinstance(event, OdometryEvent)  # the only event without a model
        if event.robot not in self.layout.robots:
            return "unknown_robot"
        if not all(map(finite, (event.x, event.y, event.yaw, event.v, event.w, event.z))):
            return "invalid_odometry"
        return None  # the time checks come after (the team clock, then the track's order)

    def is_late(self, t: float) -> bool:
        """Whether a measurement stamped ``t`` is older than the filter's time (it can no
        longer be fused)."""
        return self.grid.is_late(t)

    def memory(self, model: type) -> dict[Any, Any]:
        """A dictionary of ``model``'s validation rule (e.g. each pair's last range)."""
        return self._memory.setdefault(model, {})

    def _reject(self, reason: str, event: Event) -> None:
        self.stats["rejected_" + reason] += 1
        n = self.stats["rejected_" + reason]
        if n == 1 or n % 1000 == 0:
            log.warning("rejected %s (%s, %d so far): %r", type(event).__name__, reason, n, event)

    # ---------------------------------------------------------------- what happened
    @property
    def recovering(self) -> bool:
        """Whether the localizer judges itself lost and is recovering
        (:mod:`relloc.localizers.recovery`); never for a method without recovery."""
        return False

    def fault_counters(self) -> dict[str, Any]:
        """What the faults did (for the status and ``--json``): whether the filter is
        recovering now, how often it was found lost and re-started, clock steps followed and
        stamps rejected as outliers, odometry resets or jumps per robot, batches forced."""
        keys = (
            "divergence_detected",
            "recovery_injections",
            "clock_jumps_followed",
            "batches_forced",
            "odometry_reanchored",
            "rejected_time_jump",
            "rejected_time_jump_backward",
        )
        out: dict[str, Any] = {k.removeprefix("rejected_"): self.stats.get(k, 0) for k in keys}
        out["recovering"] = self.recovering
        out["odometry_faults"] = dict(self.odometry_faults)
        return out

    @property
    def rejected(self) -> dict[str, int]:
        return {
            k.removeprefix("rejected_"): v
            for k, v in self.stats.items()
            if k.startswith("rejected_")
        }
