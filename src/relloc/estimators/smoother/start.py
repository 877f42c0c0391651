"""The smoother's start: its orientation hypotheses and their priors.

From ranges (:func:`range_start`): the range graph's shape
(:func:`relloc.filter.range_shape.shape_from_ranges`), with odometry turned to ``ROTATIONS``
angles times two reflections (a hypothesis each, pruned later by graph cost), without it one
hypothesis whose rotation/reflection is a gauge. Without ranges (:func:`chained_start`): the
relative positions chained from the reference. :func:`merge_fixes` merges a step's measured
relative positions into one factor per observer and target; :func:`kept_by_cost` prunes the
hypotheses (the 3D smoother's too).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from relloc.estimators.smoother.graph import Relative
from relloc.filter.factors import RangeTerms, RelativeFix
from relloc.filter.range_shape import orientation_hypotheses, shape_from_ranges, start_covariance

FloatArray = NDArray[np.float64]

SHAPE_SIGMA = 0.3
"""Smallest std (m per coordinate) of the start's shape."""
WIDE_SIGMA = 10.0
"""Std (m) of the prior of a robot no range places."""
ROTATIONS = 8
"""Orientation hypotheses per handedness at the start (with odometry)."""

Start = tuple[FloatArray, FloatArray, NDArray[np.bool_], float]
"""Hypotheses' means ``(M, N, 2)`` and covariances ``(M, N, 2, 2)`` (team order, relative to
the reference), which robots are placed, the shape's RMS residual."""


def kept_by_cost(costs: FloatArray, prune: float, only_best: bool) -> list[int]:
    """The hypotheses to keep, best first: those whose graph error ``costs`` is within
    ``prune`` of the best's (a likelihood ratio of ``e^-prune``), or the best alone."""
    order = np.argsort(costs)
    keep = [int(i) for i in order if costs[i] <= costs[order[0]] + prune]
    return keep[:1] if only_best else keep


def range_start(
    n: int, ref: int, terms: RangeTerms, bias_mean: FloatArray, *, odometry: bool
) -> Start | None:
    """The range graph's shape in every orientation hypothesis: means ``(M, N, 2)``,
    covariances ``(M, N, 2, 2)``, which robots it placed, its RMS residual; ``None`` where
    it places no robot. ``odometry``: whether the shared heading frame exists (else one
    hypothesis: the orientation is a gauge)."""
    j = terms.bias
    prior = np.where(j >= 0, np.append(bias_mean, 0.0)[j], 0.0)  # the start's bias guess
    shape = shape_from_ranges(n, ref, terms.index_a, terms.index_b, terms.distance - prior)
    others = np.array([i for i in range(n) if i != ref], dtype=np.intp)
    placed = shape.placed[others]
    if shape.measured == 0 or not placed.any():
        return None
    rel = shape.relative[others]
    rotations = ROTATIONS if odometry else 1
    formations = orientation_hypotheses(rel, rotations, reflections=odometry)
    step = 2.0 * math.pi / rotations if odometry else 0.0
    cov = start_covariance(formations, max(SHAPE_SIGMA, 2.0 * shape.rms), step)
    k = others.size
    blocks = np.stack(
        [cov[:, 2 * i : 2 * i + 2, 2 * i : 2 * i + 2] for i in range(k)], axis=1
    )  # (M, K, 2, 2)
    blocks[:, ~placed] = WIDE_SIGMA**2 * np.eye(2)
    means = np.zeros((formations.shape[0], n, 2))
    means[:, others] = formations
    covs = np.tile(np.eye(2), (formations.shape[0], n, 1, 1))
    covs[:, others] = blocks
    return means, covs, shape.placed.copy(), float(shape.rms)


def merge_fixes(observed: list[RelativeFix]) -> Relative | None:
    """``observed`` (:meth:`SmootherLocalizer._observations`, the models' fixes) merged into one factor per
    observer and target: their median vector, their mean covariance undivided (a step's sightings
    share their heading error, as its ranges their bias); ``None`` if empty."""
    if not observed:
        return None
    groups: dict[tuple[int, int], list[tuple[FloatArray, FloatArray]]] = {}
    for fix in observed:
        groups.setdefault((fix.observer, fix.target), []).append((fix.vector, fix.cov))
    pairs = list(groups)
    vec = np.array([np.median([v for v, _ in groups[p]], axis=0) for p in pairs], float)
    cov = np.array([np.mean([c for _, c in groups[p]], axis=0) for p in pairs], float)
    a, b = (np.array(x, np.intp) for x in zip(*pairs, strict=True))
    return Relative(a, b, vec, cov)


def chained_start(n: int, ref: int, observed: list[RelativeFix]) -> Start | None:
    """One hypothesis from relative positions alone: each robot placed from a placed one along
    a measured vector (the reference at the origin), its prior the chain's covariance widened to
    ``SHAPE_SIGMA``; robots no chain reaches get ``WIDE_SIGMA``. ``None`` if none is reached."""
    pos = np.zeros((n, 2))
    cov = np.tile(WIDE_SIGMA**2 * np.eye(2), (n, 1, 1))
    placed = np.zeros(n, dtype=bool)
    placed[ref] = True
    cov[ref] = np.eye(2)
    grew = True
    while grew:
        grew = False
        for fix in observed:
            a, b, v, c = fix.observer, fix.target, fix.vector, fix.cov
            for src, dst, sign in ((a, b, 1.0), (b, a, -1.0)):
                if placed[src] and not placed[dst]:
                    pos[dst] = pos[src] + sign * v
                    base = cov[src] if src != ref else np.zeros((2, 2))
                    cov[dst] = base + c + SHAPE_SIGMA**2 * np.eye(2)
                    placed[dst] = grew = True
    if placed.sum() < 2:
        return None
    return pos[None], cov[None], placed, 0.0
