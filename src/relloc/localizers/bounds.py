"""Calibration bounds: odometry scales and pair biases that cannot run away.

An online calibration state is observable only through the motion and the ranges; a filter
started on a wrong solution can explain its errors by a scale of 0.04 or a bias of metres,
and then looks converged. A scale outside the physical interval ``[filter.self_calibration]
scale_min .. scale_max`` or a pair bias further than ``BIAS_BOUND_SIGMAS`` prior standard
deviations from its prior is no solution: the localizer restarts the calibration from its prior
(the positions kept, their spread back to the start's), says why, and counts it.
"""

from __future__ import annotations

from collections.abc import Mapping

from relloc.config import TeamConfig
from relloc.filter.base import FilterEstimate

BIAS_BOUND_SIGMAS = 5.0
"""How many prior standard deviations a pair bias may stray from its prior mean."""


class CalibrationBounds:
    """Says which calibration state of an estimate has left its bound, and why."""

    def __init__(self, config: TeamConfig, bias_priors: Mapping[str, tuple[float, float]]) -> None:
        sc = config.filter.self_calibration
        self.scale_min, self.scale_max = sc.scale_min, sc.scale_max
        self.bias_priors = dict(bias_priors)
        """Per bias pair, the prior (mean, std)."""

    def violation(self, fe: FilterEstimate) -> str | None:
        """The first state of ``fe`` outside its bound, as a reason line (``None``: all in)."""
        for robot, (scale, _) in sorted(fe.scales.items()):
            if not self.scale_min <= scale <= self.scale_max:
                return f"odometry scale of {robot} at {scale:.3f}, outside {self.scale_min:g}..{self.scale_max:g}"
        for pair, (bias, _) in sorted(fe.biases.items()):
            prior = self.bias_priors.get(pair)
            if prior is not None and abs(bias - prior[0]) > BIAS_BOUND_SIGMAS * prior[1]:
                return f"range bias of {pair} at {bias:.3f} m, more than {BIAS_BOUND_SIGMAS:g} sigma from its prior"
        return None
