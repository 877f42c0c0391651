"""Multilateration baseline: least-squares relative positions from the ranges present.

Ranges between robots fix the formation only up to a rotation and a reflection about the
reference robot (and nothing at all when the range graph is not rigid: a single range between
two robots gives a distance, not a relative position). ``solve`` therefore

1. checks that the graph can determine a formation (at least three robots, every robot with at
   least two ranges, and the rigidity matrix at the solution of rank ``2N - 3``), and reports
   *no estimate* otherwise;
2. starts from the previous solution when there is one, else from classical
   multidimensional scaling when all pairs are present plus a few random starts;
3. minimises the squared range residuals with SciPy's ``least_squares``;
4. turns the result about the reference onto the previous solution, so the arbitrary
   rotation stays continuous from step to step (without ground truth).

The formation is returned with the reference at the origin, in an arbitrary but continuous
gauge; evaluation fits one rotation/reflection for a whole run (see :mod:`relloc.evaluation.metrics`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix

from relloc import geometry

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def classical_mds(distances: FloatArray) -> FloatArray:
    """2-D coordinates (N, 2) whose pairwise distances best match the full matrix ``distances``."""
    n = distances.shape[0]
    j = np.eye(n) - np.ones((n, n)) / n
    b = -0.5 * j @ (distances**2) @ j
    vals, vecs = np.linalg.eigh(b)
    order = np.argsort(vals)[::-1][:2]
    return vecs[:, order] * np.sqrt(np.maximum(vals[order], 0.0))


def rigidity_rank(positions: FloatArray, pairs: IntArray) -> int:
    """Rank of the 2-D rigidity matrix of the graph ``pairs`` at ``positions``."""
    n = positions.shape[0]
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    d = positions[pairs[:, 0]] - positions[pairs[:, 1]]
    r = np.zeros((len(pairs), n, 2))
    rows = np.arange(len(pairs))
    r[rows, pairs[:, 0]] = d
    r[rows, pairs[:, 1]] = -d
    flat = r.reshape(len(pairs), 2 * n)
    return int(
        np.linalg.matrix_rank(flat, tol=1e-6 * max(1.0, float(np.abs(flat).max(initial=0.0))))
    )


def can_determine(n_robots: int, pairs: IntArray) -> bool:
    """Necessary counting conditions for a formation: >= 3 robots, >= 2N-3 ranges, degree >= 2."""
    if n_robots < 3 or len(pairs) < 2 * n_robots - 3:
        return False
    degree = np.bincount(np.asarray(pairs).ravel(), minlength=n_robots)
    return bool(np.all(degree >= 2))


FOLDED_RMS = 0.3
"""RMS range residual (m) above which a solve from the previous solution is taken for a folded
formation (a local minimum it cannot leave) and the cold starts are tried as well: several times
a range's noise, below a pair bias left uncorrected."""


def solve(
    n_robots: int,
    reference: int,
    pairs: IntArray,
    distances: FloatArray,
    initial: FloatArray | None = None,
    rng: np.random.Generator | None = None,
    *,
    unfold: bool = False,
) -> FloatArray | None:
    """Positions (N, 2) relative to ``reference``, or ``None`` when the ranges cannot fix them.

    ``initial``: the previous solution, where the solve starts. ``unfold``: where that start
    leaves the ranges more than ``FOLDED_RMS`` unexplained, try the cold starts too (a team with
    several tags on a robot: a tag a few decimetres from its sibling folds over easily)."""
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    distances = np.asarray(distances, dtype=float)
    if not can_determine(n_robots, pairs):
        return None
    free = np.array([i for i in range(n_robots) if i != reference], dtype=np.intp)

    def unpack(v: FloatArray) -> FloatArray:
        p = np.zeros((n_robots, 2))
        p[free] = v.reshape(-1, 2)
        return p

    def residuals(v: FloatArray) -> FloatArray:
        p = unpack(v)
        return geometry.distance(p[pairs[:, 0]], p[pairs[:, 1]]) - distances

    column = np.full(n_robots, -1, dtype=np.intp)
    column[free] = np.arange(free.size)
    rows = np.arange(len(pairs))

    ends = [(pairs[:, k], sign, column[pairs[:, k]] >= 0) for k, sign in ((0, 1.0), (1, -1.0))]
    jac_rows = np.concatenate([np.repeat(rows[ok], 2) for _, _, ok in ends])
    jac_cols = np.concatenate(
        [(2 * column[end[ok]][:, None] + np.arange(2)).ravel() for end, _, ok in ends]
    )

    def jacobian(v: FloatArray) -> csr_matrix:
        """``d|p_a - p_b| / dp_a = u``, ``/ dp_b = -u`` (``u`` the unit vector from b to a;
        any unit vector where they coincide), on the free robots' columns, sparse: two
        columns pairs per row, whatever the team's size."""
        p = unpack(v)
        _, u = geometry.direction(p[pairs[:, 0]] - p[pairs[:, 1]], floor=1e-12, fallback=(1.0, 0.0))
        vals = np.concatenate([(sign * u[ok]).ravel() for _, sign, ok in ends])
        return csr_matrix((vals, (jac_rows, jac_cols)), shape=(len(pairs), 2 * free.size))

    def fit(starts: list[FloatArray]) -> tuple[FloatArray | None, float]:
        best: FloatArray | None = None
        best_cost = np.inf
        for start in starts:
            s = start - start[reference]
            result = least_squares(
                residuals, s[free].ravel(), jac=jacobian, method="trf", tr_solver="lsmr"
            )
            if result.cost < best_cost:
                best, best_cost = unpack(result.x), result.cost
        return best, best_cost

    best, best_cost = (None, np.inf) if initial is None else fit([initial - initial[reference]])
    cold = False
    if best is None or (unfold and math.sqrt(2.0 * best_cost / len(pairs)) > FOLDED_RMS):
        found, cost = fit(_cold_starts(n_robots, reference, pairs, distances, rng))
        if cost < best_cost:
            best, best_cost, cold = found, cost, True
    if best is None or rigidity_rank(best, pairs) < 2 * n_robots - 3:
        return None
    if initial is not None:
        target = initial - initial[reference]
        turned = _rotate_onto(best, target)
        if cold:  # a new solution may be the mirror image of the last: keep the gauge's side
            mirrored = _rotate_onto(best * np.array([1.0, -1.0]), target)
            if np.sum((mirrored - target) ** 2) < np.sum((turned - target) ** 2):
                turned = mirrored
        best = turned
    return best


def _cold_starts(
    n_robots: int,
    reference: int,
    pairs: IntArray,
    distances: FloatArray,
    rng: np.random.Generator | None,
) -> list[FloatArray]:
    """Where a solve starts without a previous solution: classical MDS where every pair is
    ranged, and five random formations of the ranges' scale."""
    starts: list[FloatArray] = []
    full = np.full((n_robots, n_robots), np.nan)
    full[pairs[:, 0], pairs[:, 1]] = distances
    full[pairs[:, 1], pairs[:, 0]] = distances
    np.fill_diagonal(full, 0.0)
    if not np.any(np.isnan(full)):
        x = classical_mds(full)
        starts.append(x - x[reference])
    rng = rng or np.random.default_rng(0)
    scale = float(np.median(distances))
    starts += [rng.normal(scale=scale, size=(n_robots, 2)) for _ in range(5)]
    return starts


def _rotate_onto(points: FloatArray, target: FloatArray) -> FloatArray:
    """``points`` turned about the origin (a proper rotation) to best match ``target``.

    The solver is free to slide along the rotation that ranges cannot see; turning each new
    solution back onto the previous one keeps the gauge continuous (no ground truth used).
    """
    h = target.T @ points
    angle = np.arctan2(h[1, 0] - h[0, 1], h[0, 0] + h[1, 1])
    c, s = np.cos(angle), np.sin(angle)
    return points @ np.array([[c, -s], [s, c]]).T
