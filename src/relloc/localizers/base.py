"""What every localizer shares: validation, the batching grid, odometry tracks, emission.

Sensors are asynchronous: each robot's odometry, each UWB pair and each camera arrive at their
own rates and lags. A localizer

* validates every event (non-finite values, negative ranges, unknown robots, time going
  backwards): a bad event is **rejected and counted** in :attr:`Localizer.stats` (and logged),
  never allowed to crash the engine or to corrupt the estimate. The time checks are here; the
  measurement's own rule is its model's (:mod:`relloc.filter.registry`);
* keeps a **team clock** that no single stamp can capture: the first events wait until five
  of them (from two sources: robots' odometry, range pairs) are in, and their median stamp
  sets it; after that a stamp more than ``max_time_jump`` ahead of the newest accepted one, or
  behind it where it could no longer be used, is rejected and counted (``time_jump``,
  ``time_jump_backward``) and votes for a jump; three agreeing votes from two sources, each
  accepted event meanwhile taking one away, make the clock follow a step of the whole stream,
  either way (``clock_jumps_followed``; the filter's times move with it). A batch never grows
  past ``_MAX_PENDING`` (``batches_forced``);
* keeps each robot's odometry in an :class:`~relloc.odometry.OdometryTrack` (shared heading
  frame), so that it can predict to any instant; a message that moves its robot faster than
  ``max_speed``/``max_yaw_rate`` (``[filter.odometry]``) is a reset or a jump and re-anchors
  the track instead of moving the robot (``odometry_reanchored``, per robot in
  :attr:`Localizer.odometry_faults`);
* gathers the measurements stamped within one cell of a fixed ``update_period`` grid into one
  batch, predicts with every robot's odometry up to the batch time (its newest stamp), and
  fuses the batch in one update (the stacked measurement vector of the paper). A grid, not a
  window opened by the first measurement: a pair ranging at the update rate with some jitter
  then gives one range per batch, not now one, now two;
* emits an :class:`~relloc.estimate.Estimate` (each robot's position relative to the
  reference, with covariance) at ``estimate_period``.

A :class:`FilterLocalizer` also watches itself (:class:`~relloc.localizers.divergence.DivergenceMonitor`): when most of a
robot's ranges disagree with its estimate it is lost, flags its estimates ``recovering``,
counts it (``divergence_detected``) and starts again from the measurements since the
disagreement began, oriented by the last formation it trusted, dead-reckoned to now
(``recovery_injections``).

Subclasses differ only in ``_step``, the fusion of one batch. :class:`FilterLocalizer` is that
step for a filter of :mod:`relloc.filter.base`: predict, update with the batch's measurement
models, estimate, maybe resample.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter, deque
from typing import Any

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.events import (
    WAKE_ALWAYS,
    DetectionEvent,
    Event,
    GroundTruthEvent,
    OdometryEvent,
    RangeEvent,
    RelativeObservation,
    SightingEvent,
    WakeRule,
)
from relloc.filter.base import FilterEstimate, WeightedFilter
from relloc.filter.measurement import MeasurementModel, ModelContext, finite
from relloc.filter.motion import OdometryMotion
from relloc.filter.pf import ParticleFilter
from relloc.filter.registry import MODELS, model_for
from relloc.filter.state import StateLayout, TeamLayout
from relloc.filter.summary import estimate_fields
from relloc.localizers.divergence import DivergenceMonitor
from relloc.localizers.start import annealed_start, orient_by
from relloc.odometry import OdometryTrack

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
Measurement = Any
"""An event some registered measurement model consumes."""

_TIME_TOLERANCE = 1e-9
_JUMP_VOTES = 3
"""Agreeing votes (from two sources at least) before the clock follows a jump."""
_WARMUP_EVENTS = 5
"""Events (from two sources, or twice as many from one) whose median stamp sets the clock."""
_MAX_PENDING = 5000
"""A batch this large is fused at once (counted ``batches_forced``): a batch never grows."""
_SPEED_SLACK = 0.25
"""Odometry displacement (m) allowed beyond ``max_speed * dt`` (jitter over short intervals)."""
_YAW_SLACK = 0.3
"""Odometry turn (rad) allowed beyond ``max_yaw_rate * dt``."""


def _source(event: Event) -> tuple[str, ...]:
    """Which stream an event belongs to (one robot's odometry, one pair's ranges, ...)."""
    if isinstance(event, RangeEvent):
        return ("range", *sorted((event.robot_a, event.robot_b)))
    return (type(event).__name__, str(getattr(event, "robot", getattr(event, "observer", ""))))

_CONFIDENT_STD = 0.5
"""Largest position std (m) of an estimate kept as a reference formation for recovery."""
_REFERENCE_SIGMA = 0.5
"""Scale (m) of the robust fit of a re-annealed formation to the dead-reckoned reference: a
robot farther off than this (moved unseen) hardly sways the orientation."""
_RECOVERY_FRACTION = 0.5
"""Share of the hypotheses re-injected at each recovery."""
_TRUST_HOLD = 5.0
"""Seconds after a restart before its formations are trusted as the orientation reference."""
_RECOVERY_SIGMA = 1.5
"""Spread (m) of a lost robot's re-injected positions about the estimate."""

_WAKE_MARGIN = 1e-5
"""Seconds by which a :class:`WakeRule`'s bounds are moved towards waking: more than the
rounding of ``floor(t / period)`` at epoch stamps (about 4e-7 s)."""

_UNRANGED_AFTER = 2.0
"""Seconds without a range after which a robot pauses the orientation kernel."""

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
        self._clock = -math.inf  # newest accepted stamp (-inf: not set yet)
        self._warmup: list[Event] = []  # the first events, until they agree on a time
        self._sources: set[tuple[str, ...]] = set()  # sources whose events were accepted
        self._jump_candidate = math.nan  # stamp of the last vote for a clock jump
        self._jump_ahead = True  # whether that vote is for a jump forward
        self._votes = 0  # agreeing votes, less the events accepted since
        self._vote_sources: set[tuple[str, ...]] = set()
        self.odometry_faults: dict[str, int] = {}
        """Per robot, how many odometry resets or jumps re-anchored its track."""

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
        if model is None and not isinstance(event, OdometryEvent):
            self.stats["ignored_" + type(event).__name__] += 1
            return []
        if self._clock == -math.inf:
            # The first events cannot set the clock alone: they wait until enough of them
            # (from more than one source) set it by their median (the module docstring).
            self._warmup.append(event)
            if not self._warmup_ready():
                return []
            return self._end_warmup()
        return self._timed(event, model)

    def _timed(self, event: Event, model: type[MeasurementModel] | None) -> list[Estimate]:
        """An event past the checks of its own: the team clock's check, then into the filter."""
        out: list[Estimate] = []
        reason = self._clock_check(event)
        if reason == "follow":
            out += self._follow_jump(event.t - self._clock)
        elif reason is not None:
            self._reject(reason, event)
            return []
        return out + self._accept(event, model)

    def _accept(self, event: Event, model: type[MeasurementModel] | None) -> list[Estimate]:
        if self._votes:
            self._votes -= 1  # normal events wear a jump candidate down
            if not self._votes:
                self._vote_sources.clear()
        self._sources.add(_source(event))
        if isinstance(event, OdometryEvent):
            track = self.tracks[event.robot]
            if event.t <= track.last_time + _TIME_TOLERANCE:
                self._reject("out_of_order_odometry", event)
                return []
            self._clock = max(self._clock, event.t)
            if not track.empty and self._implausible(track, event):
                track.reanchor(event)
                self.stats["odometry_reanchored"] += 1
                self.odometry_faults[event.robot] = self.odometry_faults.get(event.robot, 0) + 1
                log.warning("odometry of %s jumped at t=%.3f (reset or step): track re-anchored", event.robot, event.t)
            first = track.empty
            track.add(event)
            if first:
                self.first_odometry[event.robot] = (event.t, track.pose_at(event.t)[2])
            self.stats["odometry"] += 1
            return self._advance(event.t)
        assert model is not None
        self._clock = max(self._clock, event.t)
        out: list[Estimate] = []
        if self._pending and (
            self._cell(event.t) > self._cell(self._batch_start) or len(self._pending) >= _MAX_PENDING
        ):
            if len(self._pending) >= _MAX_PENDING:
                self.stats["batches_forced"] += 1
            out += self._run_batch()
        if not self._pending:
            self._batch_start = event.t
        self._pending.append(event)
        self.stats[model.stat] += 1
        return out

    def wake_rule(self) -> WakeRule:
        """Which events could make this localizer fuse a batch now (and so emit an estimate):
        what a live server must process at once; any other event can wait and be processed
        later, in its order, with the same result (:class:`WakeRule`).

        It mirrors the batching grid of :meth:`_accept` and :meth:`_advance` for the state
        after every event processed so far. A measurement is urgent from the cell after the
        pending batch's, or always when no batch is pending (it opens one: once processed,
        the rule knows its cell) or the batch nears ``_MAX_PENDING``; odometry from two cells
        after it (never with no batch pending). Every event is urgent during the warm-up and
        outside the ``max_time_jump`` window about the clock (a vote for a jump). The bounds
        are moved by ``_WAKE_MARGIN`` towards urgent, so rounding can only wake too often.
        """
        clock = self._clock
        if clock == -math.inf:
            return WAKE_ALWAYS
        limit = self.config.filter.max_time_jump
        lo, hi = clock - limit + _WAKE_MARGIN, clock + limit - _WAKE_MARGIN
        if not self._pending:
            return WakeRule(-math.inf, math.inf, lo, hi)
        if len(self._pending) >= _MAX_PENDING // 2:
            return WakeRule(-math.inf, -math.inf, lo, hi)
        cell = self._cell(self._batch_start)
        period = self.update_period
        return WakeRule((cell + 1) * period - _WAKE_MARGIN, (cell + 2) * period - _WAKE_MARGIN, lo, hi)

    def flush(self) -> list[Estimate]:
        """Fuse what is still pending (end of a recording)."""
        out = self._end_warmup() if self._warmup else []
        return out + (self._run_batch() if self._pending else [])

    # ---------------------------------------------------------------- the team clock
    def _warmup_ready(self) -> bool:
        sources = {_source(e) for e in self._warmup}
        n = len(self._warmup)
        return n >= _WARMUP_EVENTS and (len(sources) >= 2 or n >= 2 * _WARMUP_EVENTS)

    def _end_warmup(self) -> list[Estimate]:
        """Set the clock at the median stamp of the first events, then take each of them
        through the clock's check in arrival order (an outlier among them is rejected)."""
        events, self._warmup = self._warmup, []
        self._clock = float(np.median([e.t for e in events]))
        out: list[Estimate] = []
        for ev in events:
            out += self._timed(ev, model_for(ev))
        return out

    def _clock_check(self, event: Event) -> str | None:
        """``None`` to accept ``event``'s stamp, ``"follow"`` when it completes the vote for a
        jump of the whole stream, else the rejection reason.

        A stamp more than ``max_time_jump`` ahead of the clock (the newest accepted stamp), or
        behind it where the event could no longer be used anyway, votes for a jump to its
        time. The clock follows once ``_JUMP_VOTES`` agreeing votes came from at least two
        sources (robots' odometry, range pairs; one if the team has only one), each event
        accepted meanwhile taking one vote away: one robot's wrong clock, or stray stamps
        minutes apart, never move it, a jump of the whole team does (either way).
        """
        t = event.t
        limit = self.config.filter.max_time_jump
        ahead = t > self._clock + limit
        if not ahead and t >= self._clock - limit:
            return None
        if not ahead and not self._unusable(event):
            return None  # a late source, not a clock step: the event's own checks apply
        if self._votes and abs(t - self._jump_candidate) <= limit and ahead == self._jump_ahead:
            self._votes += 1
        else:
            self._votes, self._vote_sources = 1, set()
            self._jump_ahead = ahead
        self._jump_candidate = t
        self._vote_sources.add(_source(event))
        if self._votes >= _JUMP_VOTES and len(self._vote_sources) >= min(2, max(len(self._sources), 1)):
            return "follow"
        return "time_jump" if ahead else "time_jump_backward"

    def _unusable(self, event: Event) -> bool:
        if isinstance(event, OdometryEvent):
            return event.t <= self.tracks[event.robot].last_time + _TIME_TOLERANCE
        return self.is_late(event.t)

    def _follow_jump(self, dt: float) -> list[Estimate]:
        """The whole stream's clock stepped by ``dt``: fuse what is pending, then move the
        times the filter holds by ``dt`` (its clock, the fused horizon, the last emission), so
        that the next batch predicts over the step's real length, not over the step."""
        out = self._run_batch() if self._pending else []
        log.warning("the team's clock stepped by %+.3f s: followed", dt)
        self.stats["clock_jumps_followed"] += 1
        self._votes, self._vote_sources, self._jump_candidate = 0, set(), math.nan
        self._clock += dt
        self._closed_until += dt
        self._last_emit += dt
        if dt < 0:
            # Back in time: the tracks' history moves with the clock (new odometry must come
            # after it). Forward, they stay: the first odometry after the step then spans it,
            # and a real gap in a recording keeps the motion made meanwhile.
            for track in self.tracks.values():
                track.shift_time(dt)
        self._shift_time(dt)
        return out

    def _shift_time(self, dt: float) -> None:
        """A subclass's own times moved by ``dt`` (a followed clock jump)."""

    def _implausible(self, track: OdometryTrack, event: OdometryEvent) -> bool:
        """Whether ``event`` moves its robot faster than a ground robot can (a reset, a step
        of the integrator): ``max_speed`` and ``max_yaw_rate`` of ``[filter.odometry]``, with
        a slack for jitter over short intervals."""
        oc = self.config.filter.odometry
        last = track.last_event
        if last is None:
            return False
        dt = max(event.t - last.t, 0.0)
        if track.mode == "twist":
            return abs(event.v) > oc.max_speed or abs(event.w) > oc.max_yaw_rate
        dist = math.hypot(event.x - last.x, event.y - last.y) * track.scale
        turn = abs(math.remainder(event.yaw - last.yaw, math.tau))
        return dist > oc.max_speed * dt + _SPEED_SLACK or turn > oc.max_yaw_rate * dt + _YAW_SLACK

    # ---------------------------------------------------------------- validation
    def _rejection(self, event: Event, model: type[MeasurementModel] | None) -> str | None:
        if isinstance(event, GroundTruthEvent | DetectionEvent):
            return None
        if model is None and not isinstance(event, OdometryEvent):
            return "unknown_event_type"
        if not finite(event.t):
            return "invalid_time"
        if model is not None:
            return model.rejection(event, self)
        if event.robot not in self.layout.robots:
            return "unknown_robot"
        if not all(map(finite, (event.x, event.y, event.yaw, event.v, event.w))):
            return "invalid_odometry"
        return None  # the time checks come after (the team clock, then the track's order)

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

    def _reject(self, reason: str, event: Event) -> None:
        self.stats["rejected_" + reason] += 1
        n = self.stats["rejected_" + reason]
        if n == 1 or n % 1000 == 0:
            log.warning("rejected %s (%s, %d so far): %r", type(event).__name__, reason, n, event)

    def fault_counters(self) -> dict[str, Any]:
        """What the faults did (for the status and ``--json``): whether the filter is
        recovering now, how often it was found lost and re-started, clock steps followed and
        stamps rejected as outliers, odometry resets or jumps per robot, batches forced."""
        keys = ("divergence_detected", "recovery_injections", "clock_jumps_followed", "batches_forced",
                "odometry_reanchored", "rejected_time_jump", "rejected_time_jump_backward")
        out: dict[str, Any] = {k.removeprefix("rejected_"): self.stats.get(k, 0) for k in keys}
        out["recovering"] = self.recovering
        out["odometry_faults"] = dict(self.odometry_faults)
        return out

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

    @property
    def recovering(self) -> bool:
        """Whether the localizer judges itself lost and is recovering (see
        :class:`DivergenceMonitor`); never for a method without one."""
        return False

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
        unseen = self._unseen(t)
        if unseen:
            covs = self._widen_unseen(covs, unseen)
        est = Estimate(
            t, self.method, self.layout.reference, positions, covs, fe.ess, fe.headings, fe.biases, fe.scales,
            **honest,
            recovering=self.recovering, particles=fe.particles, unseen=unseen,
        )
        self.last_estimate = est
        return est

    def _unseen(self, t: float) -> dict[str, float]:
        """Robots nothing is heard of at ``t``, with the seconds their motion has been unknown
        (see :attr:`Estimate.unseen`); none for a localizer that does not track ranges."""
        return {}

    def _widen_unseen(
        self, covs: dict[str, tuple[tuple[float, float], tuple[float, float]]], unseen: dict[str, float]
    ) -> dict[str, tuple[tuple[float, float], tuple[float, float]]]:
        """The covariances grown for what the unseen robots may have driven meanwhile: a robot
        moving at ``unseen_speed`` in an unknown direction, ``(speed * seconds)^2`` per axis;
        a relative position is unknown by its own robot's motion and by the reference's."""
        speed = self.config.filter.odometry.unseen_speed
        ref = unseen.get(self.layout.reference, 0.0)
        out = dict(covs)
        for robot, ((xx, xy), (yx, yy)) in covs.items():
            add = (speed * unseen.get(robot, 0.0)) ** 2 + (speed * ref) ** 2
            if add:
                out[robot] = ((xx + add, xy), (yx, yy + add))
        return out


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
        self.monitor = DivergenceMonitor()
        self._recent: deque[Measurement] = deque()
        self._formations: deque[tuple[float, FloatArray]] = deque()
        """Trusted formations, each less the dead reckoning ``_drift`` at its time."""
        self._drift = np.zeros(2 * self.layout.n_others)
        """The formation's motion by odometry alone since the start (shared heading frame)."""
        self._trusted_from = -math.inf
        """Formations estimated before this time are not trusted (a restart's hold)."""
        self._last_ranged: dict[str, float] = {}
        """Each robot's newest range (for the orientation kernel)."""
        self._last_measured: dict[str, float] = {}
        """Each robot's newest measurement of any kind (for :meth:`_unseen`)."""
        self._split_at = -math.inf
        """When some robot was last out of ranging."""
        self._others_index = np.array([self.layout.index(r) for r in self.layout.others], dtype=np.intp)

    @property
    def recovering(self) -> bool:
        return self.monitor.lost

    def _shift_time(self, dt: float) -> None:
        self.t += dt
        self._recent.clear()
        self._formations = deque((tf + dt, f) for tf, f in self._formations)
        self._trusted_from += dt
        self._last_ranged = {r: tr + dt for r, tr in self._last_ranged.items()}
        self._last_measured = {r: tr + dt for r, tr in self._last_measured.items()}
        self._split_at += dt
        self.monitor.shift_time(dt)
        self._init_batch = [dataclasses.replace(m, t=m.t + dt) for m in self._init_batch]

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        if not self.initialized:
            self._init_batch += batch
            first = min(m.t for m in self._init_batch)
            if t - first < self.config.filter.init_window:
                return None
            start, self._init_batch = self._init_batch, []
            self._note_measured(start, ranged=False)
            return self._start(t, start)
        disp, sigma, dt = self._motion_to(t)
        self.filter.predict(disp, sigma, dt)
        if self.filter.shared_heading:
            ref = disp[self.layout.index(self.layout.reference)]
            self._drift += (disp[self._others_index] - ref).reshape(-1)
        models = self.models(batch, self.filter)
        if not self.filter.update(models):
            self.stats["update_no_support"] += 1
        fe = self.filter.estimate()
        lost = self.monitor.observe(t, batch, fe, self)
        self._remember(t, batch, fe)
        self._note_measured(batch)
        if lost:
            self._recover(t, fe, lost)
            fe = self.filter.estimate()
        est = self._emit(t, fe)
        self._pause_kernel(t, batch)
        if self.filter.maybe_resample():
            self.stats["resampled"] += 1
        for name, count in self.filter.counters().items():
            self.stats[name] = count
        return est

    def _recover(self, t: float, fe: FilterEstimate, lost: set[str]) -> None:
        """The filter is lost: start it again (:meth:`_restart`, for a particle filter the
        annealed start of :mod:`relloc.localizers.start`) from the recent measurements since
        the disagreement began (:meth:`DivergenceMonitor.onset`: a burst's ranges are not
        fused with the clean ones after it), and give the new shape the orientation and
        handedness of the last trusted formation, moved to now by odometry
        (:func:`~relloc.localizers.start.orient_by`): the ranges fix the shape, dead
        reckoning from before the loss the orientation. Nothing
        estimated within a monitor window before the loss, or within ``_TRUST_HOLD`` after a
        restart, is trusted. A filter that cannot be re-annealed instead gets hypotheses
        re-injected about its estimate, the lost robots' positions scattered
        ``_RECOVERY_SIGMA`` wide. Either way the monitor then judges the new filter on fresh
        ranges only."""
        self.stats["recovery_injections"] += 1
        # The loss may have begun a window before it was flagged: nothing since is trusted.
        while self._formations and self._formations[-1][0] > t - self.monitor.window:
            self._formations.pop()
        reference = self._good_formation(t - self.monitor.window)
        recent = list(self._recent)
        if recent:
            onset = self.monitor.onset(lost, recent[0].t)
            recent = [m for m in recent if m.t >= onset] or recent
        if not (recent and self._restart(recent, reference)):
            others = self.layout.others
            cols = [k for k, r in enumerate(others) if r in lost or self.layout.reference in lost]
            k = max(1, int(_RECOVERY_FRACTION * self.filter.n))
            formations = np.repeat((fe.mean if reference is None else reference).reshape(1, -1), k, axis=0)
            for c in cols:
                formations[:, 2 * c : 2 * c + 2] += self.rng.normal(0.0, _RECOVERY_SIGMA, (k, 2))
            self.filter.inject(formations)
        self.monitor.restart(t)
        self._trusted_from = t + _TRUST_HOLD

    def _restart(self, recent: list[Measurement], reference: FloatArray | None) -> bool:
        """Recovery's restart from ``recent`` (the measurements since the onset), oriented by
        the ``reference`` formation (``None``: none trusted); False if the filter cannot be
        restarted from them (the recovery then re-injects hypotheses). A particle filter is
        re-annealed; subclasses with another start override this."""
        if not (isinstance(self.filter, ParticleFilter) and annealed_start(self, self.filter, recent)):
            return False
        if reference is not None:
            orient_by(self.filter, reference, _REFERENCE_SIGMA)
        return True

    def _note_measured(self, batch: list[Measurement], *, ranged: bool = True) -> None:
        """Each robot's newest measurement (ranges, sightings, relative observations: for
        :meth:`_unseen`) and, with ``ranged``, its newest range (for the orientation kernel,
        which counts from the start's end)."""
        for m in batch:
            if isinstance(m, RangeEvent):
                a, b = m.robot_a, m.robot_b
                if ranged:
                    self._last_ranged[a] = self._last_ranged[b] = m.t
            elif isinstance(m, (SightingEvent, RelativeObservation)):
                a, b = m.observer, m.target
            else:
                continue
            self._last_measured[a] = max(self._last_measured.get(a, -math.inf), m.t)
            self._last_measured[b] = max(self._last_measured.get(b, -math.inf), m.t)

    def _unseen(self, t: float) -> dict[str, float]:
        """A robot is unseen once its odometry is older than the extrapolation horizon and it
        has had no measurement for ``_UNRANGED_AFTER``: from the later of the two, nothing
        says where it went (the filter holds it where it was last seen: spreading its
        particles would thin out the whole formation's). Robots never heard at all are left
        to the filter's own prior."""
        oc = self.config.filter.odometry
        if not oc.unseen_speed:
            return {}
        out = {}
        for robot in self.layout.robots:
            track = self.tracks[robot]
            measured = self._last_measured.get(robot, -math.inf)
            if track.empty and measured == -math.inf:
                continue
            odom = track.last_time + oc.max_odom_extrapolation
            if t - measured > _UNRANGED_AFTER and t > odom:
                out[robot] = round(t - max(odom, measured), 3)
        return out

    def _pause_kernel(self, t: float, batch: list[Measurement]) -> None:
        """Pause a particle filter's orientation kernel while some robot has had no range for
        ``_UNRANGED_AFTER`` (silent, or out of range). The kernel treats the orientation as a
        static parameter of one rigid formation; a robot out of ranging splits it into parts
        whose relative orientation nothing observes, and neither a common turn (the silent
        robot dragged wherever the others' orientation drifts) nor a turn of the ranged part
        alone (measured worse, docs/faults.md) is a move of the posterior. It waits as long
        again after every robot is ranged once more: the orientations are then still the
        split's mixture."""
        if any(t - self._last_ranged.get(r, t) > _UNRANGED_AFTER for r in self.layout.robots):
            self._split_at = t
        if isinstance(self.filter, ParticleFilter):
            self.filter.kernel_paused = t - self._split_at < _UNRANGED_AFTER

    def _remember(self, t: float, batch: list[Measurement], fe: FilterEstimate) -> None:
        """Keep the last ``init_window`` of measurements (for a re-annealed start) and the
        formations the localizer trusts: those estimated while the monitor sees few outliers,
        the estimate is confident (every robot's std under ``_CONFIDENT_STD``: a filter that
        has just jumped is wide, and sees no outliers), and not within ``_TRUST_HOLD`` of a
        restart (whose orientation was borrowed from the reference, and whose shape fits only
        the ranges of its window: a burst's, perhaps). The newest trusted formation older than
        the horizon is always kept, so a long episode still has one to return to."""
        self._recent.extend(batch)
        horizon = t - max(self.config.filter.init_window, self.update_period)
        while self._recent and self._recent[0].t < horizon:
            self._recent.popleft()
        confident = float(np.linalg.eigvalsh(fe.cov).max(initial=0.0)) < _CONFIDENT_STD**2
        if self.monitor.healthy and confident and t >= self._trusted_from:
            self._formations.append((t, fe.mean.reshape(-1) - self._drift))
            keep = t - 2 * self.monitor.window - 1.0
            while len(self._formations) > 1 and self._formations[1][0] < keep:
                self._formations.popleft()

    def _good_formation(self, before: float) -> FloatArray | None:
        """The newest trusted formation estimated before ``before`` (else the oldest kept),
        moved to now by the odometry since (dead reckoning in the shared heading frame)."""
        good = [f for tf, f in self._formations if tf <= before]
        f = good[-1] if good else (self._formations[0][1] if self._formations else None)
        return None if f is None else f + self._drift

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
