"""Divergence detection: when the filter is lost, as the share of ranges its own estimate calls
outliers (issue 15's monitor, used by :class:`relloc.localizers.base.FilterLocalizer`).

A particle filter that has collapsed onto a wrong formation (a multipath burst, a robot moved
without odometry) keeps reporting a confident estimate: its own spread says nothing. The ranges
do: a filter that tracks the team sees a few disagree (NLOS, gross errors), a lost one sees most
of a robot's ranges disagree. The monitor only compares ranges with the published positions, so
it is the same for particles and Gaussians and for any robustified likelihood; what to do when
it says "lost" (a re-annealed start, re-injected hypotheses) is the localizer's business.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from relloc.events import RangeEvent, pair_key
from relloc.filter.base import FilterEstimate

if TYPE_CHECKING:
    from relloc.localizers.base import Localizer, Measurement

log = logging.getLogger(__name__)


class DivergenceMonitor:
    """Says when the filter is lost: the share of ranges that its own estimate calls outliers.

    After each update, every range of the batch is compared with the distance between its
    robots' estimated positions (less the pair's bias): a residual beyond
    ``max(_GATE_M, 3 sigma)``, sigma the range noise and the two estimates' spreads together,
    is an outlier. A filter that tracks the team sees a few (NLOS, gross errors); a lost one
    sees most of a robot's ranges disagree. Over the last ``window`` seconds, a robot whose
    ranges are outliers in more than ``lost_fraction`` of ``min_ranges`` or more is lost (the
    reference, when most of everyone's are); the state clears once every robot is under
    ``clear_fraction``; a restart that has not cleared it after a whole window of fresh ranges
    returns the robots still over ``clear_fraction`` as lost again (a retry). Tracking ranges
    keeps the rule independent of the filter (particles or Gaussians) and of how the
    likelihood is robustified.
    """

    def __init__(
        self, window: float = 1.0, lost_fraction: float = 0.6, clear_fraction: float = 0.25, min_ranges: int = 5
    ) -> None:
        self.window = window
        self.lost_fraction = lost_fraction
        self.clear_fraction = clear_fraction
        self.min_ranges = min_ranges
        self.lost = False
        self.healthy = True
        """Whether the last batches had few outliers (under ``clear_fraction``)."""
        self.episodes = 0
        """Times the filter was found lost."""
        self._seen: dict[str, deque[tuple[float, bool]]] = {}
        self._restarted = -math.inf

    def restart(self, t: float) -> None:
        """Forget the ranges seen (the filter was restarted at ``t``: judge it on fresh
        ones); the lost state stays until they clear it."""
        self._seen.clear()
        self._restarted = t

    def shift_time(self, dt: float) -> None:
        for q in self._seen.values():
            for i, (t, out) in enumerate(q):
                q[i] = (t + dt, out)
        self._restarted += dt

    def observe(self, t: float, batch: list[Measurement], fe: FilterEstimate, loc: Localizer) -> set[str]:
        """Record ``batch``'s ranges against ``fe``; the robots judged lost (empty if none)."""
        layout, config = loc.layout, loc.config
        index = {r: k for k, r in enumerate(layout.others)}
        # The hypotheses' own spread: the published covariance adds a floor for correlated
        # range errors (relloc.filter.summary) that would widen the gate by as much.
        floor = float(getattr(loc.filter, "covariance_floor", 0.0))
        for m in batch:
            if not isinstance(m, RangeEvent):
                continue
            pa, va = self._position(m.robot_a, index, fe, floor)
            pb, vb = self._position(m.robot_b, index, fe, floor)
            nodes = config.range_nodes(m)
            bias, scale, sigma = (0.0, 1.0, None) if m.corrected else config.uwb.calibration(*nodes)
            pair_bias = fe.biases.get(pair_key(*nodes))
            if pair_bias is not None and not m.corrected:
                bias = pair_bias[0]
            sig = sigma if sigma is not None else config.filter.likelihood.sigma_uwb
            residual = (m.distance - bias) / scale - math.hypot(pa[0] - pb[0], pa[1] - pb[1])
            outlier = abs(residual) > max(_GATE_M, 3.0 * math.sqrt(sig**2 + va + vb))
            for r in (m.robot_a, m.robot_b):
                self._seen.setdefault(r, deque()).append((m.t, outlier))
        lost: set[str] = set()
        unclear: set[str] = set()
        worst = 0.0
        for r, q in self._seen.items():
            while q and q[0][0] < t - self.window:
                q.popleft()
            if len(q) < self.min_ranges:
                continue
            frac = sum(o for _, o in q) / len(q)
            worst = max(worst, frac)
            if frac > self.lost_fraction:
                lost.add(r)
            elif frac >= self.clear_fraction:
                unclear.add(r)
        if self.lost and not lost and unclear and t - self._restarted >= self.window:
            # A restart that has not cleared the loss after a whole window of fresh ranges is
            # retried (its start may have fused some of the fault's last ranges).
            return unclear
        if lost and not self.lost:
            self.lost = True
            self.episodes += 1
            loc.stats["divergence_detected"] += 1
            log.warning("filter lost at t=%.2f (ranges of %s disagree with the estimate): recovering", t, sorted(lost))
        elif self.lost and not lost and worst < self.clear_fraction:
            self.lost = False
            log.info("filter recovered at t=%.2f", t)
        self.healthy = not self.lost and worst < self.clear_fraction
        return lost

    def onset(self, robots: set[str], since: float) -> float:
        """When the disagreement of ``robots``' ranges began, no earlier than ``since``: the
        change point of their outlier indicators ``o`` (a CUSUM: the stamp from which the sum
        of ``o - 1/2`` is largest), so that a restart anneals on the ranges since the fault
        began (a kidnapping, a burst) or since it ended (the end of a burst the lost filter
        had fitted), not across the change. ``since`` if nothing was recorded."""
        seen = sorted((t, o) for r in robots for t, o in self._seen.get(r, ()) if t >= since)
        if not seen:
            return since
        gain = np.cumsum([(o - 0.5) for _, o in reversed(seen)])[::-1]  # suffix sums
        return seen[int(np.argmax(gain))][0] if gain.max() > 0.0 else since

    @staticmethod
    def _position(
        robot: str, index: dict[str, int], fe: FilterEstimate, floor: float
    ) -> tuple[tuple[float, float], float]:
        k = index.get(robot)
        if k is None:
            return (0.0, 0.0), 0.0  # the reference
        c = fe.cov[k]
        return (float(fe.mean[k, 0]), float(fe.mean[k, 1])), max(float(0.5 * (c[0, 0] + c[1, 1])) - floor, 0.0)


_GATE_M = 0.5
"""Smallest residual (m) the divergence monitor calls an outlier."""
