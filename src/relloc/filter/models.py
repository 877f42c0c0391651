"""Process and measurement models, each vectorised over all particles at once.

Every measurement model is a small immutable batch of measurements that knows its own
log-likelihood ``log p(z | x)`` for all particles: ``log_likelihood(positions, particles)``
takes the robots' relative positions as coordinate planes of shape ``(2, N, M)`` (from
:meth:`StateLayout.positions`) and the particle rows themselves (for the blocks beyond the
positions, such as online range biases) and returns ``(M,)``. The filter sums the log-likelihoods of whatever arrived in one update — the
"stacked measurement vector" of the paper — so adding a sensor means adding a model here, not
editing the filter.

Range likelihood
----------------
UWB ranges are biased (0.2-0.5 m per transceiver pair), noisy, and occasionally wildly wrong
(non-line-of-sight spikes). With ``r = z - b - ||p_a - p_b||`` the residual of a range after the
pair's bias ``b``, the *symmetric* model is a Gaussian-plus-uniform mixture::

    p(r) = (1 - eps) N(r; 0, sigma^2) + eps / R

with ``eps`` the outlier fraction and ``R`` the support of the outliers. The uniform floor
bounds the damage one spike can do to a good particle.

A time-of-flight range can only be *too long* when the direct path is blocked: the signal that
arrives first took a detour. The *NLOS-aware* model (``nlos_fraction > 0``) adds that one-sided
component: a line-of-sight range has Gaussian noise; a non-line-of-sight one has, on top, a
positive excess delay ``e ~ |N(0, sigma_n^2)|`` (half-normal), so its residual is skew-normal::

    p(r) = (1 - eps_n - eps) N(r; 0, sigma^2) + eps_n SN(r; sigma, sigma_n) + eps / R
    SN(r; sigma, sigma_n) = 2/w phi(r/w) Phi(alpha r/w),  w^2 = sigma^2 + sigma_n^2,
                                                           alpha = sigma_n / sigma

(``Phi`` by its logistic approximation ``1 / (1 + exp(-1.702 x))``, within 0.01). Fitted by
maximum likelihood to the 7 238 distinct rows of the TIERS training table (per-pair median
removed), the residuals give sigma 0.077 m, sigma_n 0.28 m, eps_n 0.09 and no need of a
uniform part, 700 nats better than the best symmetric mixture (Gaussian 0.088 m + 2 % uniform):
the errors are skewed (1st percentile -0.22 m, 99th +0.50 m). A run of long ranges is thus
explained as a blocked path rather than pulling the particles 0.3 m apart, while a range that
is too *short* stays as informative as the line-of-sight noise says.

When the bias is estimated online, each particle holds a Gaussian belief ``N(mu, v)`` about it and the
range likelihood marginalises it: ``N(z - mu; ||p_a - p_b||, sigma^2 + v)``; after the weights
are updated, ``RangeBatch.kalman_update`` updates ``mu, v`` (a scalar Kalman filter per
particle and pair), weighting each range by the probability that it is line-of-sight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


def _robust_gaussian_loglik(residual: FloatArray, sigma: FloatArray, eps: float, support: float) -> FloatArray:
    """Elementwise log of ``(1-eps) N(residual; 0, sigma^2) + eps / support``.

    Computed in linear space (one ``exp`` and one ``log``, in place): exact, because the
    uniform floor keeps the sum away from zero, and about twice as fast as ``logaddexp``.
    """
    z = residual / sigma
    z *= z
    z *= -0.5
    if eps <= 0.0:
        z -= np.log(sigma) + _LOG_SQRT_2PI
        return z
    np.exp(z, out=z)
    z *= (1.0 - eps) / (sigma * np.sqrt(2.0 * np.pi))
    z += eps / support
    np.log(z, out=z)
    return z


_LOGISTIC_PROBIT = 1.702
"""``Phi(x) ~ 1 / (1 + exp(-1.702 x))``: the logistic approximation of the normal CDF."""


def _range_mixture(
    residual: FloatArray, sigma: FloatArray, eps: float, support: float, nlos_fraction: float, nlos_sigma: float
) -> tuple[FloatArray, FloatArray]:
    """Line-of-sight density and total density of the range mixture (module docstring),
    elementwise; ``sigma`` broadcasts against ``residual``. ``nlos_fraction`` 0 is the
    symmetric Gaussian-plus-uniform model."""
    z = residual / sigma
    los = np.exp(-0.5 * z * z)
    los *= (1.0 - nlos_fraction - eps) / (sigma * np.sqrt(2.0 * np.pi))
    if nlos_fraction <= 0.0:
        return los, los + eps / support
    w = np.sqrt(sigma * sigma + nlos_sigma * nlos_sigma)
    u = residual / w
    nlos = np.exp(-0.5 * u * u)
    # (2 / w) phi(u) Phi(alpha u), Phi by the logistic approximation
    nlos *= 2.0 * nlos_fraction / (w * np.sqrt(2.0 * np.pi))
    nlos /= 1.0 + np.exp(-_LOGISTIC_PROBIT * (nlos_sigma / sigma) * u)
    total = los + nlos
    total += eps / support
    return los, total


@dataclass(frozen=True)
class RangeBatch:
    """``K`` ranges between robots ``index_a[k]`` and ``index_b[k]`` (indices into the team).

    ``distance`` is the measured range, ``bias`` the pair's bias (``measured = true + bias``;
    a calibrated range scale is divided out by the caller) and ``sigma`` its noise.
    """

    index_a: IntArray
    index_b: IntArray
    distance: FloatArray
    bias: FloatArray
    sigma: FloatArray
    outlier_fraction: float = 0.1
    max_range: float = 15.0
    bias_columns: IntArray | None = None
    """Per range, the state column of the particle's bias mean (the variance is the next
    column), or -1 where the bias is the fixed ``bias``; ``None``: all fixed."""
    nlos_fraction: float = 0.0
    """Weight of the non-line-of-sight (one-sided, too long) component; 0: the symmetric
    Gaussian-plus-uniform model. ``sigma`` is then the line-of-sight noise."""
    nlos_sigma: float = 0.3
    """Scale of the NLOS excess delay (half-normal, m)."""

    def __len__(self) -> int:
        return len(self.distance)

    def _residual_and_sigma(self, positions: FloatArray, particles: FloatArray | None) -> tuple[FloatArray, FloatArray]:
        d = self.predicted(positions)
        residual = (self.distance - self.bias)[:, None] - d
        sigma = self.sigma[:, None]  # (K, 1): broadcasts against (K, M)
        if self.bias_columns is not None and particles is not None:
            online = self.bias_columns >= 0
            if np.any(online):
                cols = self.bias_columns[online]
                residual[online] -= particles[:, cols].T
                sigma = np.repeat(sigma, residual.shape[1], axis=1)
                sigma[online] = np.sqrt(self.sigma[online, None] ** 2 + particles[:, cols + 1].T)
        return residual, sigma

    def kalman_update(self, positions: FloatArray, particles: FloatArray) -> None:
        """Update each particle's online bias beliefs with this batch, in place.

        The Kalman gain is scaled by the probability that the range is an inlier under the
        robust mixture, so an NLOS spike barely moves the bias.
        """
        if self.bias_columns is None or not np.any(self.bias_columns >= 0):
            return
        online = self.bias_columns >= 0
        residual, sigma = self._residual_and_sigma(positions, particles)
        r, s = residual[online], sigma[online]
        cols = self.bias_columns[online]
        var = particles[:, cols + 1].T  # (K', M)
        los, total = _range_mixture(r, s, self.outlier_fraction, self.max_range, self.nlos_fraction, self.nlos_sigma)
        inlier = los / total
        gain = inlier * var / (s * s)
        particles[:, cols] += (gain * r).T
        particles[:, cols + 1] = ((1.0 - gain) * var).T

    def predicted(self, positions: FloatArray) -> FloatArray:
        """True distances of each particle's pairs, shape ``(K, M)``."""
        dx = positions[0, self.index_a] - positions[0, self.index_b]
        dy = positions[1, self.index_a] - positions[1, self.index_b]
        return np.sqrt(dx * dx + dy * dy)

    def log_likelihood(self, positions: FloatArray, particles: FloatArray | None = None) -> FloatArray:
        residual, sigma = self._residual_and_sigma(positions, particles)
        if self.nlos_fraction > 0.0:
            _, total = _range_mixture(
                residual, sigma, self.outlier_fraction, self.max_range, self.nlos_fraction, self.nlos_sigma
            )
            return np.log(total).sum(axis=0)
        ll = _robust_gaussian_loglik(residual, sigma, self.outlier_fraction, self.max_range)
        return ll.sum(axis=0)


@dataclass(frozen=True)
class RelativePositionBatch:
    """``K`` measured vectors ``p_target - p_observer`` in the shared heading frame.

    Produced by cooperative detections: two robots see one object at once, and
    ``R_i o_i - R_j o_j`` gives ``p_j - p_i`` (see :mod:`relloc.stages.association`).
    """

    index_observer: IntArray
    index_target: IntArray
    vector: FloatArray  # (K, 2)
    sigma: FloatArray  # (K,), per axis
    outlier_fraction: float = 0.02
    support: float = 100.0  # area (m^2) of the uniform outlier density

    def __len__(self) -> int:
        return len(self.sigma)

    def log_likelihood(self, positions: FloatArray, particles: FloatArray | None = None) -> FloatArray:
        ex = positions[0, self.index_target] - positions[0, self.index_observer] - self.vector[:, 0:1]
        ey = positions[1, self.index_target] - positions[1, self.index_observer] - self.vector[:, 1:2]
        s2 = (self.sigma**2)[:, None]
        r2 = ex * ex + ey * ey  # (K, M)
        eps = self.outlier_fraction
        if eps <= 0.0:
            return (-0.5 * r2 / s2 - np.log(2.0 * np.pi * s2)).sum(axis=0)
        dens = (1.0 - eps) / (2.0 * np.pi * s2) * np.exp(-0.5 * r2 / s2) + eps / self.support
        return np.log(dens).sum(axis=0)


@dataclass(frozen=True)
class OdometryMotion:
    """Relative-position process model driven by every robot's odometry.

    Robot ``i`` moved by ``disp[i]`` (shared heading frame) over ``dt`` seconds with
    per-axis standard deviation ``sigma[i]``. The relative position of ``i`` with respect to
    the reference ``r`` moves by ``disp[i] - disp[r]``; the reference's noise is drawn once per
    particle and shared by every relative position, as it is in reality. ``process_noise``
    (m/sqrt(s)) adds a random walk so that particles of static robots stay diverse.
    """

    process_noise: float = 0.03

    def propagate(
        self,
        particles: FloatArray,
        others: IntArray,
        reference: int,
        disp: FloatArray,
        sigma: FloatArray,
        dt: float,
        rng: np.random.Generator,
    ) -> None:
        """Move the position columns of ``particles`` (``(M, D)``, ``D >= 2(N-1)``: online-bias
        columns may follow; in place); ``others`` indexes disp/sigma rows."""
        m = particles.shape[0]
        n_others = len(others)
        rel = particles[:, : 2 * n_others].reshape(m, n_others, 2)
        own = np.sqrt(sigma[others] ** 2 + self.process_noise**2 * max(dt, 0.0))
        noise = rng.standard_normal((m, n_others, 2))
        noise *= own[None, :, None]
        noise += disp[others] - disp[reference]
        if sigma[reference] > 0.0:
            noise -= rng.standard_normal((m, 1, 2)) * sigma[reference]
        rel += noise
