"""What a measurement model gives a factor-graph estimator (the smoother): typed records.

A model of :mod:`relloc.filter.measurement` serves the particle filter with a likelihood, the
Gaussian sums with linear rows, and a factor graph with these: :class:`RelativeFix`, one
measured ``p_target - p_observer`` in the shared heading frame with its covariance, which the
smoother makes a between factor of the two robots' keys (:meth:`MeasurementModel.fixes`); and
:class:`RangeTerms`, the ranges of a batch as the smoother fuses them (team indices,
bias-corrected distance, noise, online bias).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class RelativeFix:
    """A measured ``p_target - p_observer`` (shared heading frame, team indices)."""

    observer: int
    target: int
    vector: FloatArray
    """``(2,)``, m."""
    cov: FloatArray
    """``(2, 2)``, m^2."""


@dataclass(frozen=True)
class RangeTerms:
    """Ranges as the smoother fuses them: per range the team indices of its two robots, its
    bias-corrected distance and std, and its online bias (an index of the state's online
    biases, -1 where the pair's bias is fixed)."""

    index_a: IntArray
    index_b: IntArray
    distance: FloatArray
    sigma: FloatArray
    bias: IntArray

    @classmethod
    def empty(cls) -> RangeTerms:
        none = np.zeros(0, np.intp)
        return cls(none, none, np.zeros(0), np.zeros(0), none)

    @property
    def size(self) -> int:
        return int(self.distance.size)
