"""The formation from the range graph: its shape by multidimensional scaling, and the handful of
orientation hypotheses that ranges cannot tell apart.

A uniform prior over relative positions has ``2(N-1)`` dimensions. The annealed start of the
sampled filter (:meth:`relloc.estimators.particle.filter.ParticleFilter.initialize_annealed`) finds a five-robot
formation (8 dimensions) among 20 000 particles; at twenty robots (38 dimensions) it does not
(docs/explanation/scaling.md). Yet the ranges of a team where many pairs range say almost everything about
the formation directly: with every pair, the distance matrix *is* the shape, up to the
rotations and reflections about the reference that no range can see.

The derivation: docs/explanation/internals.md, section ``relloc.filter.range_shape``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from relloc import geometry

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

SMACOF_ITERATIONS = 200
SMACOF_TOLERANCE = 1e-9
"""Relative decrease of the stress under which SMACOF stops."""
RESTARTS = 8
"""Random starts of SMACOF besides the classical one when some pairs did not range."""


@dataclass(frozen=True)
class GraphShape:
    """The formation a range graph gives: every robot's position relative to the reference
    (the reference's row is zero), up to a rotation and reflection about it."""

    relative: FloatArray  # (N, 2), team order, reference row zero
    placed: BoolArray  # (N,): connected to the reference through measured pairs
    rms: float  # root-mean-square residual of the measured distances (m)
    measured: int  # measured pairs


def distance_matrix(
    n: int, index_a: IntArray, index_b: IntArray, distance: FloatArray
) -> tuple[FloatArray, BoolArray]:
    """Symmetric distances ``(n, n)`` (median where a pair appears more than once) and which
    pairs were measured."""
    d = np.zeros((n, n))
    known = np.zeros((n, n), dtype=bool)
    a = np.minimum(index_a, index_b)
    b = np.maximum(index_a, index_b)
    keys = a * n + b
    for key in np.unique(keys):  # one entry per measured pair (at most N(N-1)/2): small
        sel = keys == key
        i, j = divmod(int(key), n)
        if i == j:
            continue
        d[i, j] = d[j, i] = float(np.median(distance[sel]))
        known[i, j] = known[j, i] = True
    return d, known


def shortest_paths(d: FloatArray, known: BoolArray) -> FloatArray:
    """All-pairs shortest path lengths over the measured edges (Floyd-Warshall, one ``(n, n)``
    step per intermediate robot); ``inf`` between robots the graph does not connect."""
    n = d.shape[0]
    g = np.where(known, d, np.inf)
    np.fill_diagonal(g, 0.0)
    for k in range(n):
        g = np.minimum(g, g[:, k : k + 1] + g[k : k + 1, :])
    return g


def classical_mds(d: FloatArray, dims: int = 2) -> FloatArray:
    """Torgerson's classical scaling of a complete distance matrix into ``dims`` dimensions
    ``(n, dims)`` (the plane by default)."""
    n = d.shape[0]
    j = np.eye(n) - 1.0 / n
    b = -0.5 * j @ (d * d) @ j
    vals, vecs = np.linalg.eigh(b)
    top = np.argsort(vals)[::-1][:dims]
    return vecs[:, top] * np.sqrt(np.maximum(vals[top], 0.0))[None, :]


def stress(x: FloatArray, d: FloatArray, w: FloatArray) -> float:
    """Weighted raw stress ``sum_{i<j} w_ij (|x_i - x_j| - d_ij)^2``."""
    dist = geometry.distance(x[:, None, :], x[None, :, :])
    return 0.5 * float(np.sum(w * (dist - d) ** 2))


def smacof(
    d: FloatArray, w: FloatArray, x0: FloatArray, iterations: int = SMACOF_ITERATIONS
) -> FloatArray:
    """Weighted SMACOF from ``x0`` (module docstring, step 3): Guttman transforms until the
    stress decreases by less than ``SMACOF_TOLERANCE`` of itself."""
    w = np.where(np.eye(d.shape[0], dtype=bool), 0.0, w)
    v = np.diag(w.sum(axis=1)) - w
    v_pinv = np.linalg.pinv(v)
    x = x0.copy()
    last = stress(x, d, w)
    for _ in range(iterations):
        dist = geometry.distance(x[:, None, :], x[None, :, :])
        ratio = np.where(dist > 1e-12, w * d / np.maximum(dist, 1e-12), 0.0)
        bmat = -ratio
        np.fill_diagonal(bmat, ratio.sum(axis=1))
        x = v_pinv @ bmat @ x
        now = stress(x, d, w)
        if last - now <= SMACOF_TOLERANCE * max(last, 1e-12):
            break
        last = now
    return x


def shape_from_ranges(
    n: int, reference: int, index_a: IntArray, index_b: IntArray, distance: FloatArray
) -> GraphShape:
    """The formation of ``n`` robots from ranges ``distance`` between ``index_a`` and
    ``index_b`` (bias removed), relative to robot ``reference`` (module docstring)."""
    d, known = distance_matrix(n, index_a, index_b, distance)
    paths = shortest_paths(d, known)
    placed = np.isfinite(paths[reference])
    idx = np.flatnonzero(placed)
    rel = np.zeros((n, 2))
    if idx.size < 2:
        return GraphShape(rel, placed, 0.0, 0)
    sub_d = paths[np.ix_(idx, idx)]
    sub_known = known[np.ix_(idx, idx)]
    w = sub_known.astype(float)
    x = smacof(sub_d, w, classical_mds(sub_d))
    if not sub_known[np.triu_indices(idx.size, 1)].all():
        # Completed distances are only upper bounds: the classical start can sit in a local
        # minimum of the stress. A few seeded random starts, the lowest stress kept.
        rng = np.random.default_rng(0)
        scale = float(np.max(sub_d[np.isfinite(sub_d)]))
        for _ in range(RESTARTS):
            y = smacof(sub_d, w, rng.uniform(-scale, scale, (idx.size, 2)))
            if stress(y, sub_d, w) < stress(x, sub_d, w):
                x = y
    ref = int(np.flatnonzero(idx == reference)[0])
    rel[idx] = x - x[ref]
    dist = geometry.distance(x[:, None, :], x[None, :, :])
    iu = np.triu_indices(idx.size, 1)
    res = (dist - sub_d)[iu][sub_known[iu]]
    return GraphShape(
        rel, placed, float(np.sqrt(np.mean(res * res))) if res.size else 0.0, int(res.size)
    )


def orientation_hypotheses(
    relative: FloatArray, rotations: int, reflections: bool = True
) -> FloatArray:
    """``relative`` ``(K, 2)`` turned about the origin (the reference) to ``rotations`` evenly
    spaced angles, and mirrored (``y -> -y`` before turning) if ``reflections``: shape
    ``(rotations * (1 + reflections), K, 2)``, the unmirrored ones first."""
    angles = 2.0 * math.pi * np.arange(rotations) / rotations
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    shapes = [relative] + ([relative * np.array([1.0, -1.0])] if reflections else [])
    out = []
    for shape in shapes:
        x, y = shape[None, :, 0], shape[None, :, 1]
        out.append(np.stack([c * x - s * y, s * x + c * y], axis=-1))
    return np.concatenate(out, axis=0)


def start_covariance(
    formations: FloatArray, shape_sigma: float, rotation_sigma: float
) -> FloatArray:
    """Covariance ``(M, 2K, 2K)`` of each hypothesis: ``shape_sigma^2`` per coordinate and,
    fully correlated across the robots, a rotation of the whole formation about the reference
    with std ``rotation_sigma`` (rad): ``shape_sigma^2 I + rotation_sigma^2 J J^T`` with
    ``J = d formation / d theta`` (each robot's ``(-y, x)``)."""
    m, k, _ = formations.shape
    jac = np.stack([-formations[:, :, 1], formations[:, :, 0]], axis=-1).reshape(m, 2 * k)
    cov = rotation_sigma**2 * jac[:, :, None] * jac[:, None, :]
    cov += shape_sigma**2 * np.eye(2 * k)[None]
    return cov
