"""What the smoother publishes of its positions: per-pair step ranges, and the moments.

Pure functions of arrays, for :mod:`relloc.estimators.smoother.localizer` (the causal estimate at every
step and the whole run smoothed afterwards publish alike):

* :func:`per_pair`: a step's ranges merged into one per robot pair, the median distance with
  the largest noise (the ranges of a step share their error: no division by their count);
* :func:`moments`: positions, covariances and the summary (:class:`ModeSummary`: shape, pair
  distances, the orientation flag). Once the orientation is resolved the covariance keeps a
  turn of the whole formation about the reference (what no fusion of ranges and odometry
  observes); before, the positions and covariances are the moments over every rotation of the
  formation (:class:`~relloc.estimate.Estimate`'s contract: a robot at ``r`` from the
  reference is on a ring, mean 0, covariance ``r^2/2`` per axis) and the shape is the
  smoother's own, continuous frame.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from relloc.filter.gauge import gauge
from relloc.filter.summary import ModeSummary
from relloc.localizers.priors import with_rotation_floor

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def flatten(
    pending: dict[tuple[int, int], list[tuple[float, float]]],
) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """``pair -> [(distance, sigma), ...]`` as four arrays, a row per range."""
    rows = [(a, b, z, w) for (a, b), vals in pending.items() for z, w in vals]
    if not rows:
        empty = np.zeros(0)
        return np.zeros(0, np.intp), np.zeros(0, np.intp), empty, empty
    a, b, z, w = zip(*rows, strict=True)
    return np.array(a, np.intp), np.array(b, np.intp), np.array(z, float), np.array(w, float)


def per_pair(
    ia: IntArray, ib: IntArray, z: FloatArray, s: FloatArray
) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """One range per pair (team indices, ``a < b``): the median distance, the largest noise."""
    lo, hi = np.minimum(ia, ib), np.maximum(ia, ib)
    pairs, inverse = np.unique(np.stack([lo, hi], axis=1), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.lexsort((z, inverse))  # by pair, then distance: each pair's median is
    counts = np.bincount(inverse, minlength=pairs.shape[0])  # the middle of its run
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    zs = z[order]
    med = 0.5 * (zs[first + (counts - 1) // 2] + zs[first + counts // 2])
    sig = np.zeros(pairs.shape[0])
    np.maximum.at(sig, inverse, s)
    return pairs[:, 0].astype(np.intp), pairs[:, 1].astype(np.intp), med, sig


def moments(
    mean: FloatArray, cov: FloatArray, observable: bool, rotation_floor: float
) -> tuple[FloatArray, FloatArray, ModeSummary]:
    """Published positions ``(K, 2)``, covariances ``(K, 2, 2)`` and summary of the smoother's
    relative positions ``mean`` with marginal covariances ``cov`` (module docstring)."""
    if observable:
        cov = with_rotation_floor(mean, cov, rotation_floor)
    summary = _summary(mean, cov, observable)
    if observable:
        return mean, cov, summary
    ring = 0.5 * (np.sum(mean**2, axis=1) + np.trace(cov, axis1=1, axis2=2))
    return np.zeros_like(mean), ring[:, None, None] * np.eye(2), summary


def _summary(mean: FloatArray, cov: FloatArray, observable: bool) -> ModeSummary:
    """Shape (the declared gauge once the orientation is known, else the smoother's own frame),
    pair distances with their std, the orientation flag."""
    k = mean.shape[0]
    if observable:
        shape = gauge(mean[None])[0]
        angle = math.atan2(mean[0, 1], mean[0, 0])
        c, s = math.cos(-angle), math.sin(-angle)
        rot = np.array([[c, -s], [s, c]])
        if k > 1 and (rot @ mean[1])[1] < 0.0:
            rot = np.diag([1.0, -1.0]) @ rot
        shape_cov = np.einsum("ij,kjl,ml->kim", rot, cov, rot)
    else:
        shape, shape_cov = mean.copy(), cov.copy()
    pos = np.vstack([np.zeros((1, 2)), mean])
    full = np.concatenate([np.zeros((1, 2, 2)), cov])
    diff = pos[:, None, :] - pos[None, :, :]
    dist = np.hypot(diff[..., 0], diff[..., 1])
    unit = diff / np.where(dist > 1e-9, dist, 1.0)[..., None]
    both = full[:, None] + full[None, :]
    var = np.einsum("ijk,ijkl,ijl->ij", unit, both, unit)
    distances = np.stack([dist, np.sqrt(np.maximum(var, 0.0))], axis=-1)
    return ModeSummary(
        mean,
        cov,
        mean.copy(),
        1.0,
        1,
        0.0 if observable else math.pi,
        observable,
        shape,
        shape_cov,
        distances,
        np.ones(1, dtype=bool),
    )
