"""Divergence detection: when the filter is lost, as the share of ranges its own estimate calls
outliers (used by :class:`relloc.localizers.recovery.Recovery`).

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
from collections import Counter, deque
from typing import Any

import numpy as np

from relloc.config import TeamConfig
from relloc.events import RangeEvent, pair_key
from relloc.filter.base import FilterEstimate
from relloc.filter.state import TeamLayout

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
        self, config: TeamConfig, layout: TeamLayout, *, window: float = 1.0, lost_fraction: float = 0.6,
        clear_fraction: float = 0.25, min_ranges: int = 5,
    ) -> None:  # fmt: skip
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
        self._outliers: Counter[str] = Counter()
        """The outliers among each robot's recorded ranges (kept with ``_seen``)."""
        self._restarted = -math.inf
        self._config = config
        self._pairs: dict[
            tuple[str, str, str | None, str | None, bool],
            tuple[int, int, float, float, float, str | None],
        ] = {}
        self._rows = {r: k for k, r in enumerate(layout.others)}

    def restart(self, t: float) -> None:
        """Forget the ranges seen (the filter was restarted at ``t``: judge it on fresh
        ones); the lost state stays until they clear it."""
        self._seen.clear()
        self._outliers.clear()
        self._restarted = t

    def shift_time(self, dt: float) -> None:
        for q in self._seen.values():
            for i, (t, out) in enumerate(q):
                q[i] = (t + dt, out)
        self._restarted += dt

    def observe(
        self, t: float, batch: list[Any], fe: FilterEstimate, floor: float = 0.0
    ) -> set[str]:
        """Record ``batch``'s ranges against ``fe`` (published with the covariance ``floor``,
        taken back out); the robots judged lost (empty if none). A new loss counts an
        ``episode``."""
        ranges = [m for m in batch if isinstance(m, RangeEvent)]
        if ranges:
            self._record(ranges, fe, floor)
        lost: set[str] = set()
        unclear: set[str] = set()
        worst = 0.0
        counts = self._outliers
        for r, q in self._seen.items():
            while q and q[0][0] < t - self.window:
                counts[r] -= q.popleft()[1]
            if len(q) < self.min_ranges:
                continue
            frac = counts[r] / len(q)
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
            log.warning(
                "filter lost at t=%.2f (ranges of %s disagree with the estimate): recovering",
                t,
                sorted(lost),
            )
        elif self.lost and not lost and worst < self.clear_fraction:
            self.lost = False
            log.info("filter recovered at t=%.2f", t)
        self.healthy = not self.lost and worst < self.clear_fraction
        return lost

    def _record(self, ranges: list[RangeEvent], fe: FilterEstimate, floor: float) -> None:
        """Judge each range of a batch and append ``(stamp, outlier)`` to both its robots'
        records, in batch order. What a range's pair contributes that does not change (robot
        rows, calibration, noise) is looked up once per pair and kept; the residuals and gates
        of the whole batch are then one NumPy expression. The same operations as one range at a
        time, in the same order (``math.hypot`` and Python's ``**``, whose last bits NumPy's
        ``hypot`` and ``square`` do not always match), so the flags are identical."""
        config, pairs, biases = self._config, self._pairs, fe.biases
        rows: list[tuple[float, ...]] = []
        names: list[str] = []
        for m in ranges:
            key = (m.robot_a, m.robot_b, m.node_a, m.node_b, m.corrected)
            pair = pairs.get(key)
            if pair is None:
                pair = pairs[key] = self._pair(m, config)
            row_a, row_b, bias, scale, sig2, bias_key = pair
            if bias_key is not None:
                pair_bias = biases.get(bias_key)
                if pair_bias is not None:
                    bias = pair_bias[0]
            rows.append((row_a, row_b, m.distance, bias, scale, sig2))
            names += (m.robot_a, m.robot_b)
        a = np.array(rows)
        ia, ib = a[:, 0].astype(np.intp), a[:, 1].astype(np.intp)
        # The reference is the last row: at the origin, no spread.
        n = fe.mean.shape[0]
        pos = np.zeros((n + 1, 2))
        pos[:n] = fe.mean
        var = np.zeros(n + 1)
        spread = 0.5 * (fe.cov[:, 0, 0] + fe.cov[:, 1, 1]) - floor
        var[:n] = np.where(spread < 0.0, 0.0, spread)  # max(spread, 0.0); NaN stays, as with max
        dx, dy = (pos[ia, 0] - pos[ib, 0]).tolist(), (pos[ia, 1] - pos[ib, 1]).tolist()
        distance = np.array([math.hypot(x, y) for x, y in zip(dx, dy, strict=True)])
        residual = (a[:, 2] - a[:, 3]) / a[:, 4] - distance
        gate = 3.0 * np.sqrt(a[:, 5] + var[ia] + var[ib])
        outlier = np.abs(residual) > np.where(gate > _GATE_M, gate, _GATE_M)  # max(_GATE_M, gate)
        stamps = [m.t for m in ranges]
        flags = outlier.tolist()
        seen, counts = self._seen, self._outliers
        for k, r in enumerate(names):  # both robots of range k // 2, in batch order
            o = flags[k >> 1]
            seen.setdefault(r, deque()).append((stamps[k >> 1], o))
            counts[r] += o

    def _pair(
        self, m: RangeEvent, config: TeamConfig
    ) -> tuple[int, int, float, float, float, str | None]:
        """What the monitor needs of a range's pair that its values do not change: its robots'
        rows (the reference's is the last), the calibration's bias and scale, the range
        variance, and the key of the pair's bias in the estimate (``None`` when corrected)."""
        rows, ref = self._rows, len(self._rows)
        nodes = config.range_nodes(m)
        bias, scale, sigma = (0.0, 1.0, None) if m.corrected else config.uwb.calibration(*nodes)
        sig = sigma if sigma is not None else config.uwb.sigma
        return (
            rows.get(m.robot_a, ref), rows.get(m.robot_b, ref), bias, scale, sig**2,
            None if m.corrected else pair_key(*nodes),
        )  # fmt: skip

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


_GATE_M = 0.5
"""Smallest residual (m) the divergence monitor calls an outlier."""
