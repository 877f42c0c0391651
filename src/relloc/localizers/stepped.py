"""The step every estimator kind's localizer runs around its state, and what it publishes.

:class:`SteppedLocalizer` gathers ``init_window`` of measurements and starts the estimator
(the subclass's ``_start``); then every batch is one ``_cycle``. It holds what every kind
shares: each robot's odometry displacement and its noise since the last step
(:meth:`~SteppedLocalizer._motion_to`), the collaborators that read an estimate, and the
emission of the honest :class:`~relloc.estimate.Estimate`:

* :class:`~relloc.localizers.watchdog.ConsistencyWatchdog` judges the published covariance
  against the estimator's own innovations (while it does not cover them the estimate says
  ``inconsistent`` and its covariance is widened);
* :class:`~relloc.localizers.heard.Heard` widens the covariances of robots nothing is heard of;
* :class:`~relloc.localizers.bounds.CalibrationBounds` (set by a kind that calibrates online)
  says when a scale or bias left its physical bound.

A weighted filter's cycle (prediction, models, recovery, resampling) is
:class:`relloc.localizers.filtered.FilterLocalizer`'s; the smoother's is its own
(:mod:`relloc.estimators.smoother`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.estimate import (
    BODY_FRAME,
    HEADING_FRAME,
    Covariance,
    Estimate,
    Position,
    covariance_of,
    position_of,
)
from relloc.filter.base import FilterEstimate
from relloc.filter.motion import OdometryMotion
from relloc.filter.state import StateLayout
from relloc.filter.summary import estimate_fields
from relloc.localizers.base import Localizer, Measurement
from relloc.localizers.bounds import CalibrationBounds
from relloc.localizers.calibration_check import CalibrationCheck
from relloc.localizers.floor import SightingFloor
from relloc.localizers.heard import Heard
from relloc.localizers.watchdog import ConsistencyWatchdog

FloatArray = NDArray[np.float64]


class SteppedLocalizer(Localizer):
    """An estimator's localizer: its start, its cycle and its estimate (module docstring)."""

    range_model: Literal["nlos", "symmetric"] = "nlos"
    """Which range likelihood (:class:`relloc.filter.measurement.ModelContext`) the estimator
    assumes (the watchdog judges ranges with the same)."""

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
        self.heard = Heard(config, self.layout)
        self.watchdog = ConsistencyWatchdog(config, self.layout)
        self.floor = SightingFloor(config)
        self.bounds: CalibrationBounds | None = None
        """The bounds of the online calibration (a filter that estimates it sets them)."""
        self.calibration_check: CalibrationCheck | None = None
        """Judges calibrated online biases against the data (a kind with a
        :class:`~relloc.localizers.priors.BiasPrior` sets it)."""
        self.calibration_restart_reason = ""
        """Why the calibration was last restarted (empty: never)."""

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
        self.heard.shift_time(dt)
        self.watchdog.shift_time(dt)
        self._init_batch = [dataclasses.replace(m, t=m.t + dt) for m in self._init_batch]

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        """Gather ``init_window`` of measurements, then start (:meth:`_start`); after the start
        every batch is a :meth:`_cycle`."""
        if not self.initialized:
            self._init_batch += batch
            first = min(m.t for m in self._init_batch)
            if t - first < self.config.filter.init_window:
                return None
            start, self._init_batch = self._init_batch, []
            self.heard.note(start, ranged=False)
            return self._start(t, start)
        return self._cycle(t, batch)

    def _cycle(self, t: float, batch: list[Measurement]) -> Estimate | None:
        """One step of the started estimator: the batch fused, an estimate (or ``None``)."""
        raise NotImplementedError

    def _start(self, t: float, batch: list[Measurement]) -> Estimate | None:
        raise NotImplementedError

    def _started(self, t: float) -> None:
        """The start is done at ``t``: odometry from now on moves the filter."""
        self.initialized = True
        self.t = t
        self._anchor = {r: self.odometry.pose(r, t) for r in self.layout.robots}

    def _motion_to(self, t: float) -> tuple[FloatArray, FloatArray, float]:
        """Every robot's odometry displacement ``(N, 2)`` and its noise ``(N,)`` since the last
        step, and the time step; the filter is at ``t`` after it."""
        n = len(self.layout.robots)
        disp = np.zeros((n, 2))
        sigma = np.zeros(n)
        dt = max(t - self.t, 0.0)
        for i, robot in enumerate(self.layout.robots):
            now = self.odometry.pose(robot, t)
            before = self._anchor.get(robot, (math.nan,) * 3)
            if math.isnan(now[0]):
                continue
            if math.isnan(before[0]):
                before = now  # odometry started since the last step: no known motion yet
            track = self.odometry.tracks[robot]
            carried = self.heard.carried.get(robot)
            back = None if carried is None else track.first_after(carried[0])
            if back is not None and self.heard.resume(robot, back):
                # its measurements followed it through its odometry's silence: it moves on
                # from the first message after it, not by the silence's displacement again
                before = self.odometry.pose(robot, back)
                self.stats["odometry_resumed"] += 1
            disp[i] = (now[0] - before[0], now[1] - before[1])
            dist = math.hypot(*disp[i])
            turn = abs(math.remainder(now[2] - before[2], math.tau))
            sigma[i] = self.motion.step_sigma(dist, turn)
            if self.heard.moving_unknown(robot, t, track):
                sigma[i] = max(sigma[i], self.heard.unseen_speed * dt)
                self.heard.carry(robot, track.last_time)
            self._anchor[robot] = now
        self.t = t
        return disp, sigma, dt

    def _emit(self, t: float, fe: FilterEstimate, body: FilterEstimate | None = None) -> Estimate:
        """The :class:`Estimate` of a filter's moments at ``t`` (and, where it estimates
        headings, each robot's odometry yaw then, for evaluating them), the covariances of
        unseen robots widened (:mod:`relloc.localizers.heard`), all of them while the
        watchdog finds the estimate inconsistent (by its :attr:`~ConsistencyWatchdog.widening`).
        With ``body`` (:meth:`_body`) the positions, covariances and shape are published in the
        reference's body frame; the headings, biases and scales stay the filter's."""
        shown = body or fe
        positions: dict[str, Position] = {}
        covs: dict[str, Covariance] = {}
        for k, robot in enumerate(self.layout.others):
            positions[robot] = position_of(shown.mean[k])
            covs[robot] = covariance_of(shown.cov[k])
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
                shown.summary,
                self.layout.reference,
                self.layout.others,
                # the published positions are the shape where the orientation is a gauge
                shape=self.shape_wanted or not shown.summary.orientation_observable,
            )
        )
        widening = self.watchdog.widening
        if widening > 1.0:
            covs = {
                r: covariance_of((widening * v for v in row) for row in c) for r, c in covs.items()
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
            yaws=fe.yaws,
        )
        if self.calibration_check is not None and fe.biases:
            self.calibration_check.judge(fe.biases, fe.offsets, self.stats)
        self.last_estimate = est
        return est
