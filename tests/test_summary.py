"""The honest posterior summary: the flag and a covering covariance on a ring, the heavier of two
modes, and a deterministic shape gauge."""

from __future__ import annotations

import numpy as np
import pytest

from relloc.filter.summary import gauge, summarize

FORMATION = np.array([[2.0, 0.5], [-1.0, 2.0], [0.5, -1.5]])  # three robots about the reference


def _turned(rel: np.ndarray, theta: np.ndarray, mirror: np.ndarray | None = None) -> np.ndarray:
    out = np.repeat(rel[None], theta.size, axis=0)
    if mirror is not None:
        out[mirror, :, 1] *= -1.0
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    x, y = out[:, :, 0].copy(), out[:, :, 1].copy()
    return np.stack([c * x - s * y, s * x + c * y], axis=-1)


def test_a_ring_posterior_is_flagged_and_its_covariance_covers_every_orientation() -> None:
    rng = np.random.default_rng(0)
    m = 5000
    rel = _turned(FORMATION, rng.uniform(-np.pi, np.pi, m), rng.random(m) < 0.5)
    rel += 0.05 * rng.standard_normal(rel.shape)
    w = np.full(m, 1.0 / m)
    for can_resolve in (False, True):
        s = summarize(rel, w, can_resolve=can_resolve)
        assert not s.orientation_observable
        assert s.orientation_std > 1.0
        # Whatever the truth's orientation and handedness, it lies inside the 95 % ellipse.
        truths = _turned(FORMATION, np.linspace(-np.pi, np.pi, 73), np.arange(73) % 2 == 0)
        for k in range(3):
            d = truths[:, k] - s.mean[k]
            nees = np.einsum("ta,ab,tb->t", d, np.linalg.inv(s.cov[k]), d)
            assert nees.max() < 5.99
    # The shape and the distances are still known.
    np.testing.assert_allclose(s.shape, gauge(FORMATION[None])[0], atol=0.02)
    np.testing.assert_allclose(s.distances[0, 1:, 0], np.hypot(*FORMATION.T), atol=0.02)
    assert s.distances[1, 2, 0] == pytest.approx(np.hypot(*(FORMATION[0] - FORMATION[1])), abs=0.02)


def test_a_two_mode_posterior_publishes_the_heavier_mode() -> None:
    rng = np.random.default_rng(1)
    m = 6000
    heavy = rng.random(m) < 0.7
    theta = np.where(heavy, 0.4, 0.4 + 2.0)
    mirror = ~heavy  # the light mode is the mirror image, turned
    rel = _turned(FORMATION, theta, mirror) + 0.05 * rng.standard_normal((m, 3, 2))
    s = summarize(rel, np.full(m, 1.0 / m))
    truth = _turned(FORMATION, np.array([0.4]))[0]
    assert s.n_modes == 2
    assert s.mode_weight == pytest.approx(0.7, abs=0.02)
    assert s.orientation_observable
    np.testing.assert_allclose(s.mean, truth, atol=0.01)
    assert np.max(np.sqrt(np.linalg.eigvalsh(s.cov))) < 0.1  # the mode's own spread only
    # The all-hypothesis mean sits where no mode is; it is kept only as a diagnostic.
    assert np.max(np.linalg.norm(s.weighted_mean - truth, axis=1)) > 0.5
    # Weights decide, not counts: make the other mode heavier.
    w = np.where(heavy, 0.2, 0.8)
    s = summarize(rel, w / w.sum())
    light = _turned(FORMATION, np.array([2.4]), np.array([True]))[0]
    np.testing.assert_allclose(s.mean, light, atol=0.01)


def test_the_shape_gauge_is_deterministic_and_blind_to_rotation_and_reflection() -> None:
    rng = np.random.default_rng(2)
    rel = FORMATION[None] + 0.03 * rng.standard_normal((2000, 3, 2))
    w = rng.random(2000)
    w /= w.sum()
    first = summarize(rel, w)
    again = summarize(rel.copy(), w.copy())
    np.testing.assert_array_equal(first.shape, again.shape)
    # The declared gauge: the first robot on +x, the second on the +y side.
    assert first.shape[0, 1] == pytest.approx(0.0, abs=1e-12) and first.shape[0, 0] > 0
    assert first.shape[1, 1] > 0
    for theta, mirror in ((1.3, False), (-2.5, True)):
        moved = np.stack([_turned(r, np.array([theta]), np.array([mirror]))[0] for r in rel])
        other = summarize(moved, w)
        np.testing.assert_allclose(other.shape, first.shape, atol=1e-9)
        np.testing.assert_allclose(other.distances, first.distances, atol=1e-9)
    np.testing.assert_allclose(first.shape, gauge(FORMATION[None])[0], atol=0.01)
