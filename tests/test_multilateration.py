"""Multilateration recovers a noise-free layout exactly and refuses what ranges cannot fix."""

from __future__ import annotations

import itertools

import numpy as np

from relloc.evaluation.metrics import orthogonal_procrustes
from relloc.filter import multilateration


def _ranges(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pairs = np.array(list(itertools.combinations(range(len(points)), 2)))
    return pairs, np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)


def test_noise_free_layout_recovered_exactly_up_to_rotation_reflection() -> None:
    truth = np.array([[0.0, 0.0], [2.0, 0.5], [-1.0, 2.5], [1.5, -2.0], [3.0, 3.0]])
    pairs, d = _ranges(truth)
    sol = multilateration.solve(5, 0, pairs, d)
    assert sol is not None
    np.testing.assert_allclose(sol[0], 0.0)
    r = orthogonal_procrustes(sol, truth)
    np.testing.assert_allclose(sol @ r.T, truth, atol=1e-6)


def test_warm_start_keeps_the_gauge_continuous() -> None:
    truth = np.array([[0.0, 0.0], [2.0, 0.5], [-1.0, 2.5], [1.5, -2.0]])
    pairs, d = _ranges(truth)
    sol = multilateration.solve(4, 0, pairs, d, initial=truth + 0.05)
    np.testing.assert_allclose(sol, truth, atol=1e-6)


def test_single_range_gives_no_estimate() -> None:
    assert multilateration.solve(2, 0, np.array([[0, 1]]), np.array([2.0])) is None


def test_too_few_ranges_give_no_estimate() -> None:
    # 4 robots need at least 5 ranges and degree >= 2 everywhere
    pairs = np.array([[0, 1], [0, 2], [1, 2], [2, 3]])
    assert multilateration.solve(4, 0, pairs, np.ones(4)) is None
