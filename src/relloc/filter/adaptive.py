"""How many particles: many while the posterior is wide, few once it is narrow (KLD-sampling).

A particle filter needs many particles only while its posterior is wide: at the start from the
uniform prior, after a divergence, and while the formation's orientation about the reference is
not observable (a team at rest: the posterior is a ring of rotations and mirror images, see
:mod:`relloc.filter.summary`). Once the posterior is one narrow mode, a few thousand particles
represent it as well as fifty thousand, at a tenth of the cost per update.

The derivation: docs/explanation/internals.md, section ``relloc.filter.adaptive``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
from numpy.typing import NDArray

from relloc.filter.base import ESS_THRESHOLD

FloatArray = NDArray[np.float64]

KLD_EPSILON = 0.05
"""KLD-sampling's bound on the Kullback-Leibler divergence of the binned sample (Fox's value)."""
KLD_QUANTILE = 0.99
"""Confidence ``1 - delta`` of that bound."""
KLD_BIN = 0.2
"""Cell side (m) of the grid over the relative positions whose occupied cells are counted: about
the range noise, so that cells resolve what the ranges resolve."""
MIN_PARTICLES_NO_KERNEL = 5000
"""Fewest particles where the orientation kernel cannot act (one non-reference robot, or
``rotation_kernel = 0``): nothing but the count then keeps the diversity of the weakly observed
bearing (capped at the full count)."""

# Odd 64-bit multipliers of a multiplicative hash of a particle's integer cell coordinates: the
# cells are counted by sorting one integer per particle instead of rows of D integers.
_HASH = np.array(
    [0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9, 0xD6E8FEB86659FD93,
     0xFF51AFD7ED558CCD, 0xC4CEB9FE1A85EC53, 0x94D049BB133111EB, 0xBF58476D1CE4E5B9],
    dtype=np.uint64,
)  # fmt: skip


def kld_bound(k: int, epsilon: float, z: float) -> int:
    """Fox's bound on the particles needed for a posterior occupying ``k`` cells: KL divergence
    below ``epsilon`` with the confidence whose normal quantile is ``z`` (module docstring)."""
    if k < 2:
        return 1
    a = 2.0 / (9.0 * (k - 1))
    return math.ceil((k - 1) / (2.0 * epsilon) * (1.0 - a + math.sqrt(a) * z) ** 3)


def occupied_cells(positions: FloatArray, bin_size: float) -> int:
    """How many cells of a grid of side ``bin_size`` (in every column) the rows of
    ``positions`` ``(M, D)`` occupy."""
    if positions.shape[0] == 0:
        return 0
    cells = np.floor(positions / bin_size).astype(np.int64).view(np.uint64)
    d = cells.shape[1]
    mult = _HASH[np.arange(d) % _HASH.size] + np.uint64(2) * (
        np.arange(d, dtype=np.uint64) // np.uint64(_HASH.size)
    )
    keys = (cells * mult).sum(axis=1, dtype=np.uint64)  # wraps modulo 2^64: a hash
    return int(np.unique(keys).size)


@dataclass(frozen=True)
class KldSampling:
    """The particle count of a resampling (module docstring): ``max_particles`` while the
    posterior is wide in a way binning cannot see, else Fox's bound on the occupied cells,
    clamped to ``[min_particles, max_particles]``."""

    min_particles: int
    max_particles: int
    epsilon: float = KLD_EPSILON
    quantile: float = KLD_QUANTILE
    bin_size: float = KLD_BIN
    mc_tolerance: float = 0.0
    ess_fraction: float = ESS_THRESHOLD

    def __post_init__(self) -> None:
        if not 1 <= self.min_particles <= self.max_particles:
            raise ValueError("need 1 <= min_particles <= max_particles")
        if not self.epsilon > 0.0 or not self.bin_size > 0.0:
            raise ValueError("epsilon and bin_size must be > 0")
        if not 0.5 < self.quantile < 1.0:
            raise ValueError("quantile must be in (0.5, 1)")

    @property
    def z(self) -> float:
        return NormalDist().inv_cdf(self.quantile)

    def monte_carlo_bound(self, sigma: float) -> int:
        """Particles for a Monte Carlo standard error of the weighted mean below
        ``mc_tolerance`` along a posterior direction of standard deviation ``sigma`` (m), with
        the effective sample size down to ``ess_fraction`` of the count before a resampling:
        ``sigma^2 / (ess_fraction tol^2)`` (0 without a tolerance)."""
        if self.mc_tolerance <= 0.0:
            return 0
        return math.ceil(sigma**2 / (self.ess_fraction * self.mc_tolerance**2))

    def size(self, kept: FloatArray, wide: bool, sigma: float = 0.0) -> int:
        """The count to resample to, given the distinct particles the resampling keeps
        (their position columns ``(K, D)``), whether the posterior is known to be wide, and
        the standard deviation of its widest direction (m)."""
        if wide:
            return self.max_particles
        n = max(
            kld_bound(occupied_cells(kept, self.bin_size), self.epsilon, self.z),
            self.monte_carlo_bound(sigma),
        )
        return int(min(max(n, self.min_particles), self.max_particles))
