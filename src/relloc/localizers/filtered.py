"""The localizer around a weighted filter of :mod:`relloc.filter.base`: its cycle.

After its start (:class:`~relloc.localizers.stepped.SteppedLocalizer`) every batch is
predicted to with every robot's odometry, fused through its measurement models, and
estimated; then the localizer's collaborators read the estimate:

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

import logging
import math

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.filter.base import FilterEstimate, WeightedFilter
from relloc.filter.measurement import MeasurementModel, ModelContext
from relloc.filter.registry import MODELS, model_for
from relloc.filter.state import StateLayout
from relloc.localizers.base import Measurement
from relloc.localizers.recovery import Recovery
from relloc.localizers.stepped import SteppedLocalizer

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)


class FilterLocalizer(SteppedLocalizer):
    """A localizer around a filter of :mod:`relloc.filter.base` (module docstring)."""

    filter: WeightedFilter

    def __init__(
        self, config: TeamConfig, layout: StateLayout | None = None, *, seed: int = 0
    ) -> None:
        super().__init__(config, layout, seed=seed)
        self.recovery = Recovery(config, self.layout, self.rng, self.stats)

    @property
    def recovering(self) -> bool:
        return self.recovery.monitor.lost

    def _shift_time(self, dt: float) -> None:
        super()._shift_time(dt)
        self.recovery.shift_time(dt)

    def _cycle(self, t: float, batch: list[Measurement]) -> Estimate | None:
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

    def _body(self, t: float, fe: FilterEstimate) -> FilterEstimate | None:
        """The filter's estimate in the reference's body frame where its own frame is not
        observed (:meth:`WeightedFilter.body_estimate`), else ``None`` (and before the
        reference's first odometry, whose yaw the body frame needs)."""
        yaw = self.odometry.pose(self.layout.reference, t)[2]
        if self.filter.shared_heading or not fe.headings or not math.isfinite(yaw):
            return None
        return self.filter.body_estimate(yaw)
