"""Calibration bounds: odometry scales, pair biases and headings that cannot run away.

An online calibration state is observable only through the motion and the ranges; a filter
started on a wrong solution can explain its errors by a scale of 0.04 or a bias of metres,
and then looks converged. A scale outside the physical interval ``[filter.self_calibration]
scale_min .. scale_max`` or a pair bias further than ``BIAS_BOUND_SIGMAS`` prior standard
deviations from its prior is no solution: the localizer restarts the calibration from its prior
(the positions kept, their spread back to the start's), says why, and counts it.

A heading has no interval: it is any angle, and it drifts with the gyro. What bounds it is its
own random walk (``heading_walk``, the reference's ``reference_heading_walk``): between two
estimates that both know it (circular spread under ``HEADING_KNOWN``) ``HEADING_WINDOW``
seconds apart, it may turn by ``BIAS_BOUND_SIGMAS`` standard deviations of the walk over that
time and of the two estimates' spreads, no more. A confident heading that turns faster ran away.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping

from relloc.config import TeamConfig
from relloc.filter.base import FilterEstimate

BIAS_BOUND_SIGMAS = 5.0
"""How many prior standard deviations a pair bias may stray from its prior mean (and standard
deviations of its walk a heading may turn)."""
HEADING_KNOWN = 0.2
"""Circular spread (rad) under which a heading is judged (about 11 deg)."""
HEADING_WINDOW = 10.0
"""Seconds between the two estimates of a heading that are compared."""


class CalibrationBounds:
    """Says which calibration state of an estimate has left its bound, and why."""

    def __init__(self, config: TeamConfig, bias_priors: Mapping[str, tuple[float, float]]) -> None:
        sc = config.filter.self_calibration
        self.scale_min, self.scale_max = sc.scale_min, sc.scale_max
        self.bias_priors = dict(bias_priors)
        """Per bias pair, the prior (mean, std)."""
        self.reference = config.reference
        self.walks = (sc.heading_walk, sc.reference_heading_walk)
        self._headings: dict[str, deque[tuple[float, float, float]]] = {}
        """Per robot, its recent known headings ``(t, mean, spread)``."""

    def restart(self) -> None:
        """The calibration restarted: the headings' history is void."""
        self._headings.clear()

    def violation(self, fe: FilterEstimate, t: float | None = None) -> str | None:
        """The first state of ``fe`` (at ``t``, for the headings) outside its bound, as a
        reason line (``None``: all in)."""
        if t is not None:
            reason = self._heading_violation(fe, t)
            if reason is not None:
                return reason
        for robot, (scale, _) in sorted(fe.scales.items()):
            if not self.scale_min <= scale <= self.scale_max:
                return f"odometry scale of {robot} at {scale:.3f}, outside {self.scale_min:g}..{self.scale_max:g}"
        for pair, (bias, _) in sorted(fe.biases.items()):
            prior = self.bias_priors.get(pair)
            if prior is not None and abs(bias - prior[0]) > BIAS_BOUND_SIGMAS * prior[1]:
                return f"range bias of {pair} at {bias:.3f} m, more than {BIAS_BOUND_SIGMAS:g} sigma from its prior"
        return None

    def _heading_violation(self, fe: FilterEstimate, t: float) -> str | None:
        for robot, (mean, spread) in sorted(fe.headings.items()):
            history = self._headings.setdefault(robot, deque())
            if not spread < HEADING_KNOWN:
                history.clear()  # not known now: judged again once it is, from then on
                continue
            history.append((t, mean, spread))
            while len(history) > 1 and t - history[1][0] >= HEADING_WINDOW:
                history.popleft()
            t0, mean0, spread0 = history[0]
            if t - t0 < HEADING_WINDOW:
                continue
            walk = self.walks[1] if robot == self.reference else self.walks[0]
            allowed = BIAS_BOUND_SIGMAS * math.sqrt(
                walk * walk * (t - t0) + spread * spread + spread0 * spread0
            )
            turn = abs(math.remainder(mean - mean0, math.tau))
            if turn > allowed:
                history.clear()
                return (
                    f"heading of {robot} turned {math.degrees(turn):.0f} deg in {t - t0:.0f} s, more than "
                    f"{BIAS_BOUND_SIGMAS:g} sigma of its walk ({math.degrees(allowed):.0f} deg)"
                )
        return None
