"""The online self-check of learned range corrections: no ground truth, the team's geometry.

A model that was right in its training session can be wrong in the next one, and nothing in
the model says so. The team can: for a pair ``(a, b)``, the other robots' published positions
and the ranges from ``a`` and from ``b`` to them place ``a`` and ``b`` without the pair's own
range (a least-squares trilateration of each, started at the published position), so their
distance ``d`` is a prediction the pair's own range does not enter directly. Each range of the pair has two
candidates, the corrected range and the range less only the pair's constant, and both
innovations ``candidate - d`` are scored. Over the last ``WINDOW`` seconds per node pair, a
correction whose median squared innovation exceeds the constant's by ``OFF_RATIO`` (each with
``FLOOR`` squared added, so two small figures do not flip it on noise; the median, so a blocked
path's long range does not decide it) is switched off, the
pair then gets the constant; it is switched back on when it beats the constant by
``ON_RATIO`` (still scored while off). Every switch is counted and logged.

Why not the filter's own innovations: the estimate absorbs most of a pair's error (a 0.3 m
offset on one of the simulated team's ten pairs moved the published distance by 0.2 m), after
which the wrong correction fits it better than the right constant. A pair whose robots have
fewer than ``MIN_ANCHORS`` other ranged robots (two robots, one range), or whose positions
are not yet known to ``MAX_STD``, is not judged.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from relloc.estimate import Estimate

log = logging.getLogger(__name__)

WINDOW = 5.0
"""Seconds of innovations a pair is judged on."""
MIN_COUNT = 10
"""Fewest scored ranges of a pair in the window before it is judged."""
OFF_RATIO = 1.5
"""Switch off where the correction's median squared innovation exceeds the constant's this much."""
ON_RATIO = 1.0 / 1.5
"""Switch back on where it is below the constant's times this."""
FLOOR = 0.05
"""Metres added in quadrature to both sides of the comparison: the trilateration's own error."""
MAX_AGE = 0.5
"""Seconds an estimate or another pair's range may be older than the range it helps score."""
MIN_ANCHORS = 2
"""Other robots with a fresh range to ``a`` (and to ``b``) that a trilateration needs (two
leave a mirror solution, which the start at the published position rules out)."""
MAX_STD = 0.3
"""Metres of published std above which a robot's position is not used (a filter still
converging judges nothing)."""
ITERATIONS = 5
"""Gauss-Newton steps of each trilateration."""


@dataclass
class _Pair:
    scored: deque[tuple[float, float, float]] = field(default_factory=deque)
    """``(t, corrected innovation^2, constant innovation^2)``."""
    off: bool = False


class CorrectionCheck:
    """Per node pair, whether its learned correction is on (module docstring)."""

    def __init__(self) -> None:
        self._pairs: dict[str, _Pair] = {}
        self._last: Estimate | None = None
        self._ranges: dict[frozenset[str], tuple[float, float]] = {}
        """Robot pair -> ``(t, distance the filter was given)`` of its latest range."""
        self.switched_off = 0
        self.switched_on = 0

    def enabled(self, pair: str) -> bool:
        state = self._pairs.get(pair)
        return state is None or not state.off

    @property
    def off_pairs(self) -> list[str]:
        """The pairs whose correction is off now, sorted."""
        return sorted(p for p, s in self._pairs.items() if s.off)

    def used(self, t: float, robot_a: str, robot_b: str, distance: float) -> None:
        """The filter was given ``distance`` between the robots at ``t`` (any pair)."""
        self._ranges[frozenset((robot_a, robot_b))] = (t, distance)

    def note(
        self, pair: str, t: float, robot_a: str, robot_b: str, corrected: float, constant: float
    ) -> bool:
        """A range of ``pair`` at ``t``: its two candidate distances scored against the
        distance the other robots imply, then the pair judged; whether it was switched."""
        d = self._predicted(t, robot_a, robot_b)
        if d is None:
            return False
        state = self._pairs.setdefault(pair, _Pair())
        state.scored.append((t, (corrected - d) ** 2, (constant - d) ** 2))
        while state.scored and state.scored[0][0] < t - WINDOW:
            state.scored.popleft()
        return len(state.scored) >= MIN_COUNT and self._decide(pair, state)

    def judge(self, estimate: Estimate) -> None:
        """The filter published ``estimate``: the next ranges are scored with it."""
        self._last = estimate

    def _predicted(self, t: float, a: str, b: str) -> float | None:
        """``|p_a - p_b|`` with each placed from the others without the pair's range."""
        last = self._last
        if last is None or not 0.0 <= t - last.t <= MAX_AGE:
            return None
        positions = {r: p for r, p in last.positions.items() if _settled(last, r)}
        positions[last.reference] = (0.0, 0.0)
        if a not in positions or b not in positions:
            return None
        placed = []
        for robot, other in ((a, b), (b, a)):
            anchors, ranges = [], []
            for c, p in positions.items():
                got = self._ranges.get(frozenset((robot, c)))
                if c not in (robot, other) and got is not None and t - got[0] <= MAX_AGE:
                    anchors.append(p)
                    ranges.append(got[1])
            if len(anchors) < MIN_ANCHORS:
                return None
            placed.append(
                _trilaterate(
                    np.array(positions[robot], float),
                    np.array(anchors, float),
                    np.array(ranges, float),
                )
            )
        return float(np.hypot(*(placed[0] - placed[1])))

    def _decide(self, pair: str, state: _Pair) -> bool:
        """Switch the pair off or on where its window says so; whether it did."""
        scored = np.array(state.scored)
        corrected = float(np.median(scored[:, 1])) + FLOOR**2
        constant = float(np.median(scored[:, 2])) + FLOOR**2
        if not state.off and corrected > OFF_RATIO * constant:
            state.off = True
            self.switched_off += 1
            log.warning(
                "range correction of %s switched off: RMS innovation %.3f m corrected, %.3f m with the constant",
                pair,
                math.sqrt(corrected),
                math.sqrt(constant),
            )
            return True
        if state.off and corrected < ON_RATIO * constant:
            state.off = False
            self.switched_on += 1
            log.warning("range correction of %s switched back on", pair)
            return True
        return False


def _settled(estimate: Estimate, robot: str) -> bool:
    """Whether ``robot``'s published covariance has no std above ``MAX_STD``."""
    cov = estimate.covariances.get(robot)
    return cov is not None and max(cov[0][0], cov[1][1]) <= MAX_STD**2


def _trilaterate(start: np.ndarray, anchors: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """The point whose distances to ``anchors`` ``(K, 2)`` best match ``ranges`` ``(K,)``
    (Gauss-Newton from ``start``)."""
    p = start.copy()
    for _ in range(ITERATIONS):
        diff = p - anchors
        dist = np.maximum(np.hypot(diff[:, 0], diff[:, 1]), 1e-6)
        jac = diff / dist[:, None]
        step, *_ = np.linalg.lstsq(jac, ranges - dist, rcond=None)
        p = p + step
    return p
