"""The consistency watchdog: does the published covariance still cover the filter's own
innovations?

A filter can be wrong and confident at once (a start on the wrong solution, a calibration that
ran away) while the divergence monitor's gross-outlier rule (:mod:`.divergence`) stays quiet.
The watchdog uses only what the filter sees: after each update, every fused range and every
sighting's range is compared with the distance between its robots' published positions, and
its normalised innovation squared ``NIS = (z - b - d)^2 / S`` is taken, ``S`` the
measurement's variance plus both positions' published covariances along the line of sight.
A sighting's bearing is compared with the direction between them less the observer's yaw in
the published frame (its odometry yaw, turned by its published heading where the filter
estimates headings, whose variance then counts too), ``S`` the bearing's variance plus the
positions' covariances across the line of sight over the distance squared; where the filter
has neither a shared frame nor headings, the bearing is not fused and not judged.
For a consistent filter each measurement's NIS (a sighting's range and bearing summed) is
chi-square with as many degrees of freedom as it has rows. Each measurement counts for both its
robots. Over the last ``WINDOW`` seconds, the estimate is *inconsistent* when more than
``FLAG_SHARE`` of some robot's (at least ``MIN_COUNT``) measurements exceed their chi-square
99 % bound (:data:`CHI2_BOUND`): a consistent filter puts 1 % there, so the rule holds for any session and tolerates up to half
of a robot's measurements being outliers (NLOS, gross errors). It clears once every robot's
share is under ``CLEAR_SHARE``. While inconsistent, the
published covariance is widened by :attr:`ConsistencyWatchdog.widening`, the worst robot's
median NIS over the chi-square median (what the innovations say the spread is).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from relloc.config import TeamConfig
from relloc.events import RangeEvent, SightingEvent, pair_key
from relloc.filter.base import FilterEstimate
from relloc.filter.state import TeamLayout

WINDOW = 5.0
"""Seconds of innovations judged together: flagged well within 10 s of the onset."""
MIN_COUNT = 10
"""Fewest measurements of a robot in the window for a judgement."""
CHI2_BOUND = {1: 6.635, 2: 9.210}
"""The chi-square 99 % quantile by degrees of freedom."""
CHI2_MEDIAN = {1: 0.4549, 2: 1.3863}
"""The chi-square median by degrees of freedom."""
FLAG_SHARE = 0.5
"""Share of the window's NIS over ``CHI2_1_BOUND`` that flags (1 % when consistent)."""
CLEAR_SHARE = 0.25
"""Share under which a flag clears."""


class ConsistencyWatchdog:
    """Normalised innovations of the fused ranges and sightings against their chi-square bound."""

    def __init__(self, config: TeamConfig, layout: TeamLayout) -> None:
        self.config = config
        self._rows = {r: k for k, r in enumerate(layout.others)}
        self._nis: dict[str, deque[tuple[float, float, bool]]] = {}
        """Each robot's recent ``(stamp, NIS over its chi-square median, over its bound)``."""
        self._worst = ""
        """The robot whose share over the bound is largest."""
        self.inconsistent = False
        self.episodes = 0
        """Times the estimate was found inconsistent."""
        self._since = -math.inf
        """When the window began to count (the last restart)."""

    @property
    def widening(self) -> float:
        """The factor the published covariance is widened by while inconsistent (else 1)."""
        values = [v for _, v, _ in self._nis.get(self._worst, ())]
        if not self.inconsistent or not values:
            return 1.0
        return max(1.0, float(np.median(values)))

    def restart(self, t: float) -> None:
        """The filter was started again at ``t``: judge it on fresh innovations only; the flag
        stays until they clear it."""
        self._nis.clear()
        self._since = t

    def shift_time(self, dt: float) -> None:
        self._nis = {r: deque((t + dt, v, o) for t, v, o in q) for r, q in self._nis.items()}
        self._since += dt

    def observe(self, t: float, batch: list[Any], fe: FilterEstimate, yaws: dict[str, float] | None = None) -> bool:
        """Record ``batch``'s innovations against the published ``fe`` (``yaws``: each robot's
        odometry yaw at ``t`` where the filter has a shared frame or estimates headings, for
        the bearings); whether the localizer should restart: the estimate is newly found
        inconsistent, or a flag has outlived a whole fresh window (the restart did not help)."""
        for m in batch:
            judged = self._nis_of(m, fe, yaws)
            if judged:
                value, dof = sum(v for _, _, v in judged), len(judged)
                entry = (m.t, value / CHI2_MEDIAN[dof], value > CHI2_BOUND[dof])
                for robot in judged[0][:2]:
                    self._nis.setdefault(robot, deque()).append(entry)
        shares = {}
        for robot, q in self._nis.items():
            while q and q[0][0] < t - WINDOW:
                q.popleft()
            if len(q) >= MIN_COUNT:
                shares[robot] = sum(o for _, _, o in q) / len(q)
        if not shares:
            return False
        self._worst = max(shares, key=lambda r: shares[r])
        share = shares[self._worst]
        if share > FLAG_SHARE:
            if not self.inconsistent:
                self.inconsistent = True
                self.episodes += 1
                return True
            return t - self._since >= WINDOW
        if share < CLEAR_SHARE:
            self.inconsistent = False
        return False

    def _nis_of(self, m: Any, fe: FilterEstimate, yaws: dict[str, float] | None) -> list[tuple[str, str, float]]:
        """The robots and NIS of a range, or of a sighting's range and bearing, one per row
        (none for anything else)."""
        if isinstance(m, RangeEvent):
            if m.corrected:
                bias, scale, sigma = 0.0, 1.0, None
            else:
                nodes = self.config.range_nodes(m)
                bias, scale, sigma = self.config.uwb.calibration(*nodes)
                online = fe.biases.get(pair_key(*nodes))
                if online is not None:
                    bias = online[0]
            var = (sigma if sigma is not None else self.config.uwb.sigma) ** 2
            a, b = m.robot_a, m.robot_b
            return self._judged(a, b, fe, (m.distance - bias) / scale, var, None)
        if isinstance(m, SightingEvent):
            bearing = None
            if m.bearing is not None and yaws is not None and math.isfinite(yaws.get(m.observer, math.nan)):
                yaw, yaw_var = yaws[m.observer], 0.0
                heading = fe.headings.get(m.observer)
                if heading is not None:
                    yaw, yaw_var = yaw + heading[0], heading[1] ** 2
                bearing = (m.bearing + yaw, m.sigma_bearing**2 + yaw_var)
            r_var = None if m.range is None else m.sigma_range**2
            return self._judged(m.target, m.observer, fe, m.range, r_var, bearing)
        return []

    def _judged(
        self, a: str, b: str, fe: FilterEstimate, r: float | None, r_var: float | None,
        bearing: tuple[float, float] | None,
    ) -> list[tuple[str, str, float]]:
        """The NIS of a distance ``r`` (variance ``r_var``) between ``a`` and ``b`` and of the
        direction from ``b`` to ``a`` in the published frame, ``bearing`` as (angle,
        variance)."""
        pa, ca = self._position(a, fe)
        pb, cb = self._position(b, fe)
        d = pa - pb
        dist = float(math.hypot(d[0], d[1]))
        if dist < 1e-6:
            return []
        u = d / dist
        c = ca + cb
        out = []
        if r is not None and r_var is not None:
            out.append((a, b, (r - dist) ** 2 / (r_var + float(u @ c @ u))))
        if bearing is not None:
            n = np.array([-u[1], u[0]])
            residual = math.remainder(bearing[0] - math.atan2(d[1], d[0]), math.tau)
            out.append((a, b, residual**2 / (bearing[1] + float(n @ c @ n) / dist**2)))
        return out

    def _position(self, robot: str, fe: FilterEstimate) -> tuple[np.ndarray, np.ndarray]:
        k = self._rows.get(robot)
        if k is None:  # the reference: the origin, exactly
            return np.zeros(2), np.zeros((2, 2))
        return fe.mean[k], fe.cov[k]
