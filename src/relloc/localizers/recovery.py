"""Recovery: a filter that watches itself, and starts again when it is lost.

The :class:`~relloc.localizers.divergence.DivergenceMonitor` says when most of a robot's ranges
disagree with the estimate. The localizer then flags its estimates ``recovering``, counts it
(``divergence_detected``) and starts the filter again (``recovery_injections``) from the
measurements since the disagreement began, oriented by the last formation it trusted, moved to
now by dead reckoning: the ranges fix the shape, odometry from before the loss the
orientation. How a filter starts again is its own (``WeightedFilter.restart``: a particle
filter re-anneals); one that cannot gets hypotheses re-injected about its estimate instead.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.filter.base import FilterEstimate, WeightedFilter
from relloc.filter.state import TeamLayout
from relloc.localizers.divergence import DivergenceMonitor
from relloc.localizers.grid import UPDATE_PERIOD

FloatArray = NDArray[np.float64]
Restart = Callable[[list[Any], FloatArray | None], bool]
"""Start the filter again from recent measurements, oriented by a reference formation (or
``None``); False if it cannot."""

_CONFIDENT_STD = 0.5
"""Largest position std (m) of an estimate kept as a reference formation for recovery."""
_RECOVERY_FRACTION = 0.5
"""Share of the hypotheses re-injected at each recovery."""
_TRUST_HOLD = 5.0
"""Seconds after a restart before its formations are trusted as the orientation reference."""
_RECOVERY_SIGMA = 1.5
"""Spread (m) of a lost robot's re-injected positions about the estimate."""


class Recovery:
    """The divergence monitor, the recent measurements, the trusted formations, the restart."""

    def __init__(
        self, config: TeamConfig, layout: TeamLayout, rng: np.random.Generator, stats: Counter[str]
    ) -> None:
        self.layout, self.rng, self.stats = layout, rng, stats
        self.horizon = max(config.filter.init_window, UPDATE_PERIOD)
        """Seconds of measurements kept for a restart."""
        self.monitor = DivergenceMonitor(config, layout)
        self.recent: deque[Any] = deque()
        """The last ``init_window`` of measurements (for a restart)."""
        self.formations: deque[tuple[float, FloatArray]] = deque()
        """Trusted formations, each less the dead reckoning ``drift`` at its time."""
        self.drift = np.zeros(2 * layout.n_others)
        """The formation's motion by odometry alone since the start (shared heading frame)."""
        self.trusted_from = -np.inf
        """Formations estimated before this time are not trusted (a restart's hold)."""
        self._others = np.array([layout.index(r) for r in layout.others], dtype=np.intp)
        self._reference = layout.index(layout.reference)

    def moved(self, disp: FloatArray) -> None:
        """Every robot's odometry displacement ``(N, 2)`` in the shared heading frame."""
        self.drift += (disp[self._others] - disp[self._reference]).reshape(-1)

    def observe(self, t: float, batch: list[Any], fe: FilterEstimate, floor: float) -> set[str]:
        """The monitor's judgement of the estimate ``fe`` after ``batch``: the robots lost."""
        episodes = self.monitor.episodes
        lost = self.monitor.observe(t, batch, fe, floor)
        if self.monitor.episodes > episodes:
            self.stats["divergence_detected"] += 1
        return lost

    def remember(self, t: float, batch: list[Any], fe: FilterEstimate) -> None:
        """Keep the recent measurements and the formations the localizer trusts: those
        estimated while the monitor sees few outliers, the estimate is confident (every
        robot's std under ``_CONFIDENT_STD``: a filter that has just jumped is wide, and sees
        no outliers), and not within ``_TRUST_HOLD`` of a restart (whose orientation was
        borrowed from the reference, and whose shape fits only the ranges of its window: a
        burst's, perhaps). The newest trusted formation older than the horizon is always
        kept, so a long episode still has one to return to."""
        self.recent.extend(batch)
        horizon = t - self.horizon
        while self.recent and self.recent[0].t < horizon:
            self.recent.popleft()
        confident = float(np.linalg.eigvalsh(fe.cov).max(initial=0.0)) < _CONFIDENT_STD**2
        if self.monitor.healthy and confident and t >= self.trusted_from:
            self.formations.append((t, fe.mean.reshape(-1) - self.drift))
            keep = t - 2 * self.monitor.window - 1.0
            while len(self.formations) > 1 and self.formations[1][0] < keep:
                self.formations.popleft()

    def recover(
        self, t: float, fe: FilterEstimate, lost: set[str], target: WeightedFilter, restart: Restart
    ) -> None:
        """``target`` is lost: ``restart`` it from the recent measurements since the
        disagreement began (:meth:`DivergenceMonitor.onset`: a burst's ranges are not fused
        with the clean ones after it), oriented by the last trusted formation. Nothing
        estimated within a monitor window before the loss, or within ``_TRUST_HOLD`` after a
        restart, is trusted. Where it cannot be restarted, hypotheses are re-injected about
        the estimate, the lost robots' positions scattered ``_RECOVERY_SIGMA`` wide. Either
        way the monitor then judges the new filter on fresh ranges only."""
        self.stats["recovery_injections"] += 1
        while self.formations and self.formations[-1][0] > t - self.monitor.window:
            self.formations.pop()
        reference = self._good_formation(t - self.monitor.window)
        recent = list(self.recent)
        if recent:
            onset = self.monitor.onset(lost, recent[0].t)
            recent = [m for m in recent if m.t >= onset] or recent
        if not (recent and restart(recent, reference)):
            others = self.layout.others
            cols = [k for k, r in enumerate(others) if r in lost or self.layout.reference in lost]
            k = max(1, int(_RECOVERY_FRACTION * target.n))
            formations = np.repeat(
                (fe.mean if reference is None else reference).reshape(1, -1), k, axis=0
            )
            for c in cols:
                formations[:, 2 * c : 2 * c + 2] += self.rng.normal(0.0, _RECOVERY_SIGMA, (k, 2))
            target.inject(formations)
        self.monitor.restart(t)
        self.trusted_from = t + _TRUST_HOLD

    def _good_formation(self, before: float) -> FloatArray | None:
        """The newest trusted formation estimated before ``before`` (else the oldest kept),
        moved to now by the odometry since (dead reckoning in the shared heading frame)."""
        good = [f for tf, f in self.formations if tf <= before]
        f = good[-1] if good else (self.formations[0][1] if self.formations else None)
        return None if f is None else f + self.drift

    def shift_time(self, dt: float) -> None:
        """The team's clock stepped by ``dt``: the recent measurements are dropped (their
        stamps are of the old clock), the remembered times move."""
        self.recent.clear()
        self.formations = deque((tf + dt, f) for tf, f in self.formations)
        self.trusted_from += dt
        self.monitor.shift_time(dt)
