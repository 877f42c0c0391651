"""Log-weight arithmetic and resampling, as plain functions of weights.

Weights are kept as log-weights: with tens of ranges in one update the raw likelihoods
under-flow long before the posterior does. ``normalize`` turns log-weights into probabilities
with the log-sum-exp trick; ``ess`` is the effective sample size ``1 / sum(w^2)``.

Systematic resampling draws one uniform ``u ~ U[0, 1/M)`` and takes the particles at the
points ``u + k/M``: it is unbiased (each particle is copied ``M w_i`` times in expectation) and
has the lowest variance of the classic schemes for the cost of one cumulative sum (no search).

The particle filter's step uses compiled forms of both (:func:`renormalize_into`,
:func:`systematic_take`): one or two passes each instead of a NumPy call per operation, which
at a few hundred particles costs more than the arithmetic.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from relloc.filter import compiled

FloatArray = NDArray[np.float64]


def log_normalize(logw: FloatArray) -> FloatArray:
    """Log-weights shifted so that ``exp`` sums to one."""
    m = np.max(logw)
    if not np.isfinite(m):
        raise FloatingPointError("all particle weights are zero or non-finite")
    return logw - (m + np.log(np.sum(np.exp(logw - m))))


def normalize(logw: FloatArray) -> FloatArray:
    """Normalised weights from log-weights."""
    return np.exp(log_normalize(logw))


def ess(logw: FloatArray) -> float:
    """Effective sample size of (unnormalised) log-weights, between 1 and ``len(logw)``."""
    w = normalize(logw)
    return float(1.0 / np.sum(w * w))


def reinjection_slots(
    n: int, reinject_fraction: float, rng: np.random.Generator
) -> NDArray[np.intp]:
    """A ``reinject_fraction`` of the slots of ``n`` particles, drawn without replacement: the
    ones a filter re-draws from its prior after a resampling."""
    k = round(reinject_fraction * n)
    return rng.choice(n, size=k, replace=False) if k > 0 else np.zeros(0, dtype=np.intp)


def mixture_moments(w: FloatArray, mu: FloatArray, var: FloatArray) -> tuple[float, float]:
    """Mean and standard deviation of a mixture with normalised weights ``w``, component means
    ``mu`` and component variances ``var`` (each ``(M,)``): the law of total variance."""
    mean = float(w @ mu)
    return mean, math.sqrt(max(float(w @ (var + (mu - mean) ** 2)), 0.0))


def systematic_resample(
    weights: FloatArray, rng: np.random.Generator, n: int | None = None
) -> NDArray[np.intp]:
    """Indices of ``n`` (default ``len(weights)``) particles drawn by systematic resampling;
    ``weights`` must be normalised (non-negative, summing to one)."""
    m = len(weights) if n is None else n
    u = rng.random()
    cumulative = np.cumsum(weights)
    cumulative /= cumulative[-1]  # guard against round-off leaving the last point uncovered
    # Particle i is copied once for every point u + k (k integer) in (m c_{i-1}, m c_i]:
    # the difference of floor(m c_i - u) counts them, with no search.
    edges = np.floor(m * cumulative - u).astype(np.intp)
    counts = np.empty_like(edges)
    counts[0] = edges[0] - int(np.floor(-u))
    np.subtract(edges[1:], edges[:-1], out=counts[1:])
    return np.repeat(np.arange(len(weights)), counts)


@compiled.njit(cache=True)
def renormalize_into(logw: FloatArray, w: FloatArray) -> bool:
    """In place: ``logw`` (unnormalised, non-finite entries taken as ``-inf``) normalised so
    that ``exp`` sums to one, and ``w`` set to that ``exp``; False (``logw`` then holds the
    ``-inf``-mapped values, ``w`` is undefined) when no entry is finite."""
    top = -np.inf
    for i in range(logw.shape[0]):
        v = logw[i]
        if not math.isfinite(v):
            v = -np.inf
            logw[i] = v
        if v > top:
            top = v
    if top == -np.inf:
        return False
    total = 0.0
    for i in range(logw.shape[0]):
        e = math.exp(logw[i] - top)
        w[i] = e
        total += e
    shift = top + math.log(total)
    inv = 1.0 / total
    for i in range(logw.shape[0]):
        logw[i] -= shift
        w[i] *= inv
    return True


@compiled.njit(cache=True)
def systematic_take(weights: FloatArray, u: float, rows: FloatArray, out: FloatArray) -> None:
    """Systematic resampling as one pass: ``out`` (``(n, D)``) gets row ``i`` of ``rows`` once for
    every point ``(u + k) / n`` in its cumulative-weight interval, as
    :func:`systematic_resample` with the same ``u`` draws them (``weights`` non-negative, not
    necessarily normalised)."""
    n, width = out.shape
    total = 0.0
    for i in range(weights.shape[0]):
        total += weights[i]
    scale = n / total
    cumulative = 0.0
    previous = math.floor(-u)
    j = 0
    for i in range(weights.shape[0]):
        cumulative += weights[i]
        edge = math.floor(min(cumulative * scale, n) - u)
        copies = int(edge - previous)
        previous = edge
        for _ in range(min(copies, n - j)):
            for c in range(width):  # element by element: a row slice per copy is slower
                out[j, c] = rows[i, c]
            j += 1
    last = weights.shape[0] - 1
    while j < n:  # round-off could leave the last point uncovered: the last row takes it
        for c in range(width):
            out[j, c] = rows[last, c]
        j += 1
