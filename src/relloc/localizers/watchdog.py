"""The consistency watchdog: does the published covariance still cover the filter's own
innovations?

A filter can be wrong and confident at once (a wrong start, a runaway calibration, a robot
displaced unseen by its odometry) while the divergence monitor's gross-outlier rule
(:mod:`.divergence`) stays quiet. After each update every fused range, and each sighting's
range and bearing, is compared with the published estimate as a normalised innovation
(NIS), using what the filter's own likelihood assumes of the error.

Each robot keeps a CUSUM of "the innovations' variance is ``LAMBDA`` times what is published"
against "as published", with each NIS clipped at its 99 % bound so that isolated outliers
never accumulate. The estimate is *inconsistent* once a robot's sum passes ``THRESHOLD``
(false alarms rarer than one a day at 100 measurements a second) and clears once every sum is
back to zero and under ``CLEAR_SHARE`` of the last ``WINDOW`` seconds' measurements exceed
their bound. While inconsistent, the published covariance is widened by
:attr:`ConsistencyWatchdog.widening`.

The NIS terms and the CUSUM's bounds derived: ``docs/explanation/internals.md``.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from relloc.config import TeamConfig
from relloc.events import RangeEvent, SightingEvent, pair_key
from relloc.filter.base import FilterEstimate
from relloc.filter.ranges import GROSS_FRACTION, NLOS_FRACTION, NLOS_SIGMA, pair_sigma, separable
from relloc.filter.state import TeamLayout

WINDOW = 5.0
"""Seconds of innovations behind the clearing and the widening; a flag that outlives a fresh
window after a restart asks for another."""
MIN_COUNT = 10
"""Fewest measurements of a robot in the window for the clearing share."""
CHI2_BOUND = {1: 6.635, 2: 9.210}
"""The chi-square 99 % quantile by degrees of freedom."""
CHI2_MEDIAN = {1: 0.4549, 2: 1.3863}
"""The chi-square median by degrees of freedom."""
LAMBDA = 4.0
"""The alternative of the CUSUM: the innovations' variance this many times the published one
(their spread twice what the covariance says)."""
THRESHOLD = 16.0
"""The CUSUM's alarm level (log-likelihood ratio): a consistent filter's mean run to a false
alarm is over ``exp(THRESHOLD)`` measurements."""
CLEAR_SHARE = 0.25
"""Share of the window's NIS over the bound under which a flag clears."""


def evidence(nis: float, dof: int) -> float:
    """What one measurement's ``nis`` (``dof`` rows) adds to the CUSUM: the log-likelihood ratio
    of ``LAMBDA`` times the published variance against it, the NIS clipped at its 99 % bound."""
    return 0.5 * dof * -math.log(LAMBDA) + 0.5 * min(nis, CHI2_BOUND[dof]) * (1.0 - 1.0 / LAMBDA)


class ConsistencyWatchdog:
    """Normalised innovations of the fused ranges and sightings against their chi-square bound."""

    def __init__(self, config: TeamConfig, layout: TeamLayout) -> None:
        self.config = config
        self._rows = {r: k for k, r in enumerate(layout.others)}
        self.range_model = config.filter.likelihood.range_model
        """The range likelihood of the filter judged: the config's, which the particle filter and
        the range graph use; a localizer with another (the self-calibrating filter's symmetric
        one) sets its own here."""
        self.particle_biases = False
        """Whether the filter's online biases are carried by particles (the sampled filter sets
        it), which :func:`~relloc.filter.ranges.separable` lets keep the NLOS-aware model."""
        self._nis: dict[str, deque[tuple[float, float, bool]]] = {}
        self._over: dict[str, int] = {}
        """Per robot, how many of ``_nis``'s entries are over their bound (kept with it)."""
        self._pairs: dict[tuple[str, str, str, str, str], tuple[str, float, float, float]] = {}
        """Per range's robots, nodes and range model: its node pair, calibrated bias, scale and
        noise (:meth:`_range_model`; the config does not change under a watchdog)."""
        """Each robot's recent ``(stamp, NIS over its chi-square median, over its bound)``."""
        self._cusum: dict[str, float] = {}
        """Each robot's CUSUM of :func:`evidence`."""
        self.inconsistent = False
        self.episodes = 0
        """Times the estimate was found inconsistent."""
        self._since = -math.inf
        """When the window began to count (the last restart)."""
        self._lists: tuple[FilterEstimate, list[list[float]], list[list[list[float]]]] | None
        self._lists = None
        """The estimate :meth:`_position` last read and its means and covariances as lists;
        dropped at the end of :meth:`observe`."""

    @property
    def widening(self) -> float:
        """The factor the published covariance is widened by while inconsistent (else 1)."""
        if not self.inconsistent:
            return 1.0
        medians = [float(np.median([v for _, v, _ in q])) for q in self._nis.values() if q]
        return max([1.0, *medians])

    def restart(self, t: float) -> None:
        """The filter was started again at ``t``: judge it on fresh innovations only; the flag
        stays until they clear it."""
        self._nis.clear()
        self._over.clear()
        self._cusum.clear()
        self._since = t

    def shift_time(self, dt: float) -> None:
        """Every stamp moved by ``dt`` (a clock step of the stream)."""
        self._nis = {r: deque((t + dt, v, o) for t, v, o in q) for r, q in self._nis.items()}
        self._since += dt

    def observe(
        self,
        t: float,
        batch: list[Any],
        fe: FilterEstimate,
        yaws: dict[str, float] | None = None,
        prior: FilterEstimate | None = None,
    ) -> bool:
        """Record ``batch``'s innovations against the published ``fe``, or against ``prior``
        where given (the filter's estimate after the prediction to ``t``, before ``batch``'s
        update: the innovations before the filter absorbed them); ``yaws``: each robot's
        odometry yaw at ``t`` where the filter has a shared frame or estimates headings, for
        the bearings. Whether the localizer should restart: the estimate is newly found
        inconsistent, or a flag has outlived a whole fresh window (the restart did not help)."""
        judge = fe if prior is None else prior
        for m in batch:
            judged = self._nis_of(m, judge, yaws)
            if judged:
                value, dof = sum(v for _, _, v in judged), len(judged)
                entry = (m.t, value / CHI2_MEDIAN[dof], value > CHI2_BOUND[dof])
                step = evidence(value, dof)
                for robot in judged[0][:2]:
                    self._nis.setdefault(robot, deque()).append(entry)
                    self._over[robot] = self._over.get(robot, 0) + entry[2]
                    self._cusum[robot] = max(0.0, self._cusum.get(robot, 0.0) + step)
        self._lists = None  # the estimate is not kept beyond its step
        shares = {}
        for robot, q in self._nis.items():
            while q and q[0][0] < t - WINDOW:
                self._over[robot] -= q.popleft()[2]
            if len(q) >= MIN_COUNT:
                shares[robot] = self._over[robot] / len(q)
        if any(s > THRESHOLD for s in self._cusum.values()):
            if not self.inconsistent:
                self.inconsistent = True
                self.episodes += 1
                return True
            return t - self._since >= WINDOW
        if (
            self.inconsistent
            and shares
            and not any(self._cusum.values())
            and max(shares.values()) < CLEAR_SHARE
        ):
            self.inconsistent = False
        return False

    def _nis_of(
        self, m: Any, fe: FilterEstimate, yaws: dict[str, float] | None
    ) -> list[tuple[str, str, float]]:
        """The robots and NIS of a range, or of a sighting's range and bearing, one per row
        (none for anything else)."""
        if isinstance(m, RangeEvent):
            r, var = self._range_model(m, fe)
            return self._judged(m.robot_a, m.robot_b, fe, r, var, None)
        if isinstance(m, SightingEvent):
            bearing = None
            if (
                m.bearing is not None
                and yaws is not None
                and math.isfinite(yaws.get(m.observer, math.nan))
            ):
                yaw, yaw_var = yaws[m.observer], 0.0
                heading = fe.headings.get(m.observer)
                if heading is not None:
                    yaw, yaw_var = yaw + heading[0], heading[1] ** 2
                bearing = (m.bearing + yaw, m.sigma_bearing**2 + yaw_var)
            r_var = None if m.range is None else m.sigma_range**2
            return self._judged(m.target, m.observer, fe, m.range, r_var, bearing)
        return []

    def _range_model(self, m: RangeEvent, fe: FilterEstimate) -> tuple[float, float]:
        """A range's distance less what the filter's own likelihood expects of its error (the
        pair's bias, and the mean of the one-sided NLOS part), and that error's variance as the
        filter assumes it (:mod:`relloc.filter.ranges`): the pair's noise (an uncalibrated pair's
        widened by ``default_bias_sigma``, :func:`~relloc.filter.ranges.pair_sigma`), the NLOS
        part's spread where the NLOS-aware model applies, and the published variance of a bias
        estimated online. The uniform floor (gross errors) is left to the clip of :func:`evidence`."""
        uwb = self.config.uwb
        if m.corrected:
            sigma = max(
                uwb.sigma, m.sigma if m.sigma is not None and math.isfinite(m.sigma) else 0.0
            )
            return m.distance, sigma**2
        model = self.range_model
        known = self._pairs.get((m.robot_a, m.robot_b, m.node_a, m.node_b, model))
        if known is None:
            nodes = self.config.range_nodes(m)
            key = pair_key(*nodes)
            bias, scale, _ = uwb.calibration(*nodes)
            known = (
                key,
                bias,
                scale,
                pair_sigma(self.config, key, uwb.los_sigma if model == "nlos" else uwb.sigma),
            )
            self._pairs[(m.robot_a, m.robot_b, m.node_a, m.node_b, model)] = known
        key, bias, scale, sigma = known
        online = fe.biases.get(key)
        if online is not None:  # the bias in the state: its published variance, no widening
            separate = separable(uwb, key, in_state=not self.particle_biases)
            model = "nlos" if model == "nlos" and separate else "symmetric"  # as RangeBatch.build
            r, extra = m.distance - online[0], online[1] ** 2
            sigma = uwb.los_sigma if model == "nlos" else uwb.sigma
        else:
            r, extra = (m.distance - bias) / scale, 0.0
        if model != "nlos":
            return r, sigma**2 + extra
        share = NLOS_FRACTION / (1.0 - GROSS_FRACTION)  # of the mixture less its uniform floor
        # the skew-normal NLOS part: mean NLOS_SIGMA sqrt(2/pi), second moment sigma^2 + NLOS_SIGMA^2
        mean = share * NLOS_SIGMA * math.sqrt(2.0 / math.pi)
        return r - mean, sigma**2 + share * NLOS_SIGMA**2 - mean**2 + extra

    def _judged(
        self,
        a: str,
        b: str,
        fe: FilterEstimate,
        r: float | None,
        r_var: float | None,
        bearing: tuple[float, float] | None,
    ) -> list[tuple[str, str, float]]:
        """The NIS of a distance ``r`` (variance ``r_var``) between ``a`` and ``b`` and of the
        direction from ``b`` to ``a`` in the published frame, ``bearing`` as (angle,
        variance). In Python floats (a few per range: NumPy calls on 2-vectors cost more than
        their arithmetic), in the order the matrix products take."""
        pa, ca = self._position(a, fe)
        pb, cb = self._position(b, fe)
        dx, dy = pa[0] - pb[0], pa[1] - pb[1]
        dist = math.hypot(dx, dy)
        if dist < 1e-6:
            return []
        ux, uy = dx / dist, dy / dist
        c00, c01 = ca[0][0] + cb[0][0], ca[0][1] + cb[0][1]
        c10, c11 = ca[1][0] + cb[1][0], ca[1][1] + cb[1][1]
        out = []
        if r is not None and r_var is not None:
            along = (ux * c00 + uy * c10) * ux + (ux * c01 + uy * c11) * uy
            mean, var = self._distance(a, b, fe, dist, along)
            out.append((a, b, (r - mean) ** 2 / (r_var + var)))
        if bearing is not None:
            nx, ny = -uy, ux
            across = (nx * c00 + ny * c10) * nx + (nx * c01 + ny * c11) * ny
            residual = math.remainder(bearing[0] - math.atan2(dy, dx), math.tau)
            out.append((a, b, residual**2 / (bearing[1] + across / dist**2)))
        return out

    def _distance(
        self, a: str, b: str, fe: FilterEstimate, dist: float, along: float
    ) -> tuple[float, float]:
        """The mean and variance of the distance between ``a`` and ``b``: over the filter's
        dominant mode where it says (the pair's own, which the common rotation and translation
        of the formation do not widen, and whose mean is not pulled in by a spread of
        directions, as the distance between mean positions is), else ``dist`` between the
        published positions and ``along``, both covariances along the line of sight."""
        if fe.summary is None:
            return dist, along
        i, j = self._rows.get(a, -1) + 1, self._rows.get(b, -1) + 1
        mean, std = fe.summary.distances[i, j]
        return float(mean), float(std) ** 2

    def _position(self, robot: str, fe: FilterEstimate) -> tuple[list[float], list[list[float]]]:
        """``robot``'s published position and covariance in ``fe`` as lists (those of the last
        estimate asked about are kept: a batch's ranges all read the same one)."""
        k = self._rows.get(robot)
        if k is None:  # the reference: the origin, exactly
            return _ORIGIN
        lists = self._lists
        if lists is None or lists[0] is not fe:
            lists = self._lists = (fe, fe.mean.tolist(), fe.cov.tolist())
        return lists[1][k], lists[2][k]


_ORIGIN = ([0.0, 0.0], [[0.0, 0.0], [0.0, 0.0]])
"""The reference's position and covariance (:meth:`ConsistencyWatchdog._position`)."""
