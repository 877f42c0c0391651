"""The localizer around a filter of :mod:`relloc.filter.base`: the step every filter method runs.

After its start (subclasses' ``_start``, once ``init_window`` of measurements has been
gathered) every batch is predicted to with every robot's odometry, fused through its
measurement models, and estimated; then the localizer's collaborators read the estimate:

* :class:`~relloc.localizers.recovery.Recovery` watches for divergence and restarts the
  filter when it is lost (``WeightedFilter.restart``; the range-graph localizer overrides
  :meth:`FilterLocalizer._restart`);
* :class:`~relloc.localizers.watchdog.ConsistencyWatchdog` judges the published covariance
  against the filter's own innovations: while it does not cover them the estimate says
  ``inconsistent``, its covariance is widened, and the recovery restarts the filter;
* :class:`~relloc.localizers.bounds.CalibrationBounds` says when an online scale or bias has
  left its physical bound: the calibration then restarts from its prior
  (:meth:`FilterLocalizer._restart_calibration`);
* :class:`~relloc.localizers.heard.Heard` widens the covariances of robots nothing is heard of
  and tells the filter whether the formation is split (``WeightedFilter.pause_kernel``).

The estimate is emitted (each robot's position relative to the reference, with covariance)
and the filter resamples when due.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.estimate import BODY_FRAME, HEADING_FRAME, Estimate
from relloc.filter.base import FilterEstimate, WeightedFilter
from relloc.filter.measurement import MeasurementModel, ModelContext
from relloc.filter.motion import OdometryMotion
from relloc.filter.registry import MODELS, model_for
from relloc.filter.state import StateLayout
from relloc.filter.summary import estimate_fields
from relloc.localizers.base import Localizer, Measurement
from relloc.localizers.bounds import CalibrationBounds
from relloc.localizers.floor import SightingFloor
from relloc.localizers.heard import Heard
from relloc.localizers.recovery import Recovery
from relloc.localizers.watchdog import ConsistencyWatchdog

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)


class FilterLocalizer(Localizer):
    """A localizer around a filter of :mod:`relloc.filter.base` (module docstring)."""

    filter: WeightedFilter
    range_model: Literal["nlos", "symmetric"] = "nlos"
    """Which range likelihood (:class:`relloc.filter.measurement.ModelContext`) the filter uses."""

    def __init__(
        self, config: TeamConfig, layout: StateLayout | None = None, *, seed: int = 0
    ) -> None:
        super().__init__(config, layout)
        self.rng = np.random.default_rng(seed)
        self.motion = OdometryMotion()
        self.initialized = False
        self.t = math.nan
        self._anchor: dict[str, tuple[float, float, float]] = {}
        self._init_batch: list[Measurement] = []
        self.recovery = Recovery(config, self.layout, self.rng, self.stats)
        self.heard = Heard(config, self.layout)
        self.watchdog = ConsistencyWatchdog(config, self.layout)
        self.floor = SightingFloor(config)
        self.bounds: CalibrationBounds | None = None
        """The bounds of the online calibration (a filter that estimates it sets them)."""
        self.calibration_restart_reason = ""
        """Why the calibration was last restarted (empty: never)."""

    @property
    def recovering(self) -> bool:
        return self.recovery.monitor.lost

    @property
    def inconsistent(self) -> bool:
        """Whether the published covariance no longer covers the filter's innovations
        (:mod:`relloc.localizers.watchdog`)."""
        return self.watchdog.inconsistent

    def fault_counters(self) -> dict[str, Any]:
        """The base's, and the watchdog's: inconsistent now, episodes, restarts."""
        out = super().fault_counters()
        out["inconsistent"] = self.inconsistent
        out["inconsistency_detected"] = self.watchdog.episodes
        out["inconsistency_restarts"] = self.stats.get("inconsistency_restarts", 0)
        out["calibration_restarts"] = self.stats.get("calibration_restarts", 0)
        if self.calibration_restart_reason:
            out["calibration_restart_reason"] = self.calibration_restart_reason
        return out

    def _shift_time(self, dt: float) -> None:
        self.t += dt
        self.recovery.shift_time(dt)
        self.heard.shift_time(dt)
        self.watchdog.shift_time(dt)
        self._init_batch = [dataclasses.replace(m, t=m.t + dt) for m in self._init_batch]

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        if not self.initialized:
            self._init_batch += batch
            first = min(m.t for m in self._init_batch)
            if t - first < self.config.filter.init_window:
                return None
            start, self._init_batch = self._init_batch, []
            self.heard.note(start, ranged=False)
            return self._start(t, start)
        disp, sigma, dt = self._motion_to(t)
        self.filter.predict(disp, sigma, dt)
        if self.filter.shared_heading:
            self.recovery.moved(disp)
        models = self.models(batch, self.filter)
        floor = getattr(self.filter, "covariance_floor", None)
        if floor is not None:
            self.filter.covariance_floor = self.floor.observe(batch, floor)  # type: ignore[attr-defined]
        if not self.filter.update(models):
            self.stats["update_no_support"] += 1
        fe = self.filter.estimate()
        lost = self.recovery.observe(
            t, batch, fe, float(getattr(self.filter, "covariance_floor", 0.0))
        )
        self.recovery.remember(t, batch, fe)
        self.heard.note(batch)
        framed = self.filter.shared_heading or bool(fe.headings)
        yaws = {r: self.odometry.pose(r, t)[2] for r in self.layout.robots} if framed else None
        body = self._body(t, fe)
        if self.watchdog.observe(t, batch, body or fe, yaws):
            self.stats["inconsistency_restarts"] += 1
            lost = lost or set(self.layout.others)
        if lost:
            self.recovery.recover(t, fe, lost, self.filter, self._restart)
            self.watchdog.restart(t)
            fe = self.filter.estimate()
            body = self._body(t, fe)
        reason = None if self.bounds is None else self.bounds.violation(fe, t)
        if reason is not None and self._restart_calibration():
            log.warning("calibration restarted at t=%.2f: %s", t, reason)
            self.stats["calibration_restarts"] += 1
            self.calibration_restart_reason = reason
            self.watchdog.restart(t)
            fe = self.filter.estimate()
            body = self._body(t, fe)
        est = self._emit(t, fe, body)
        self.filter.pause_kernel(self.heard.split(t))
        if self.filter.maybe_resample():
            self.stats["resampled"] += 1
        for name, count in self.filter.counters().items():
            self.stats[name] = count
        return est

    def _restart(self, recent: list[Measurement], reference: FloatArray | None) -> bool:
        """Recovery's restart from ``recent`` (the measurements since the onset), oriented by
        the ``reference`` formation (``None``: none trusted): the filter's own
        (``WeightedFilter.restart``); False if it cannot (hypotheses are then re-injected)."""
        return self.filter.restart(recent, reference, self)

    def _restart_calibration(self) -> bool:
        """Start the online calibration again from its prior (:mod:`relloc.localizers.bounds`);
        False where the filter estimates none."""
        return False

    def _start(self, t: float, batch: list[Measurement]) -> Estimate | None:
        raise NotImplementedError

    def _started(self, t: float) -> None:
        """The start is done at ``t``: odometry from now on moves the filter."""
        self.initialized = True
        self.t = t
        self._anchor = {r: self.odometry.pose(r, t) for r in self.layout.robots}

    # ---------------------------------------------------------------- models
    def models(
        self,
        batch: list[Measurement],
        target: WeightedFilter,
        *,
        robust: bool = True,
        count: bool = True,
    ) -> list[MeasurementModel]:
        """The measurement models of ``batch`` for ``target``'s state layout, in registry
        order. Measurements in the shared heading frame are left out (and counted, with
        ``count``) where the localizer's filter has no such frame."""
        groups: dict[type, list[Measurement]] = {}
        for m in batch:
            cls = model_for(m)
            if cls is not None:
                groups.setdefault(cls, []).append(m)
        yaws = (
            {r: self.odometry.pose(r, max(m.t for m in batch))[2] for r in self.layout.robots}
            if batch
            else None
        )
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

    # ---------------------------------------------------------------- prediction, emission
    def _motion_to(self, t: float) -> tuple[FloatArray, FloatArray, float]:
        """Every robot's odometry displacement ``(N, 2)`` and its noise ``(N,)`` since the last
        step, and the time step; the filter is at ``t`` after it."""
        n = len(self.layout.robots)
        disp = np.zeros((n, 2))
        sigma = np.zeros(n)
        for i, robot in enumerate(self.layout.robots):
            now = self.odometry.pose(robot, t)
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

    def _body(self, t: float, fe: FilterEstimate) -> FilterEstimate | None:
        """The filter's estimate in the reference's body frame where its own frame is not
        observed (:meth:`WeightedFilter.body_estimate`), else ``None`` (and before the
        reference's first odometry, whose yaw the body frame needs)."""
        yaw = self.odometry.pose(self.layout.reference, t)[2]
        if self.filter.shared_heading or not fe.headings or not math.isfinite(yaw):
            return None
        return self.filter.body_estimate(yaw)

    def _emit(self, t: float, fe: FilterEstimate, body: FilterEstimate | None = None) -> Estimate:
        """The :class:`Estimate` of a filter's moments at ``t`` (and, where it estimates
        headings, each robot's odometry yaw then, for evaluating them), the covariances of
        unseen robots widened (:mod:`relloc.localizers.heard`), all of them while the
        watchdog finds the estimate inconsistent (by its :attr:`~ConsistencyWatchdog.widening`).
        With ``body`` (:meth:`_body`) the positions, covariances and shape are published in the
        reference's body frame; the headings, biases and scales stay the filter's."""
        shown = body or fe
        positions, covs = {}, {}
        for k, robot in enumerate(self.layout.others):
            positions[robot] = (float(shown.mean[k, 0]), float(shown.mean[k, 1]))
            c = shown.cov[k]
            covs[robot] = ((float(c[0, 0]), float(c[0, 1])), (float(c[1, 0]), float(c[1, 1])))
        for robot in {
            *fe.headings,
            self.layout.reference,
        }:  # the reference's: body-frame evaluation
            self.odometry.log_yaw(robot, t)
        # The shape and distances a published estimate carries (a step whose estimate is not
        # emitted leaves them uncomputed, :class:`~relloc.filter.summary.DeferredSummary`).
        honest = (
            {}
            if shown.summary is None or not self.publishes(t)
            else estimate_fields(
                shown.summary, self.layout.reference, self.layout.others, shape=self.shape_wanted
            )
        )
        widening = self.watchdog.widening
        if widening > 1.0:
            covs = {
                r: (
                    (widening * c[0][0], widening * c[0][1]),
                    (widening * c[1][0], widening * c[1][1]),
                )
                for r, c in covs.items()
            }
        unseen = self.heard.unseen(t, self.tracks)
        if unseen:
            covs = self.heard.widen(covs, unseen)
        est = Estimate(
            t,
            self.method,
            self.layout.reference,
            positions,
            covs,
            fe.ess,
            fe.headings,
            fe.biases,
            fe.scales,
            **honest,
            recovering=self.recovering,
            inconsistent=self.inconsistent,
            particles=fe.particles,
            unseen=unseen,
            frame=HEADING_FRAME if body is None else BODY_FRAME,
        )
        self.last_estimate = est
        return est
