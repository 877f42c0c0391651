"""Unit tests of the filter's pure-NumPy parts: resampling, models, prior, annealing."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from relloc.estimators.particle.filter import ParticleFilter
from relloc.filter.motion import OdometryMotion
from relloc.filter.ranges import RangeBatch
from relloc.filter.resampling import (
    ess,
    log_normalize,
    normalize,
    renormalize_into,
    systematic_resample,
    systematic_take,
)
from relloc.filter.state import StateLayout
from relloc.filter.vectors import RelativePositionBatch


def test_log_normalize_sums_to_one_without_underflow() -> None:
    logw = np.array([-1000.0, -1001.0, -1002.0])
    w = normalize(logw)
    assert w.sum() == pytest.approx(1.0)
    assert w[0] > w[1] > w[2] > 0
    assert np.exp(log_normalize(logw)).sum() == pytest.approx(1.0)


def test_ess_bounds() -> None:
    assert ess(np.zeros(100)) == pytest.approx(100.0)
    one_hot = np.full(100, -np.inf)
    one_hot[3] = 0.0
    assert ess(one_hot) == pytest.approx(1.0)


def test_systematic_resampling_preserves_weights_in_expectation() -> None:
    rng = np.random.default_rng(0)
    w = rng.random(50)
    w /= w.sum()
    counts = np.zeros(50)
    trials = 4000
    for _ in range(trials):
        counts += np.bincount(systematic_resample(w, rng), minlength=50)
    np.testing.assert_allclose(counts / (trials * 50), w, atol=2e-3)
    # systematic resampling copies each particle floor(M w) or ceil(M w) times
    idx = systematic_resample(w, rng)
    c = np.bincount(idx, minlength=50)
    assert np.all(c >= np.floor(50 * w) - 1e-9) and np.all(c <= np.ceil(50 * w) + 1e-9)


def test_layout_positions_put_reference_at_origin() -> None:
    layout = StateLayout(("a", "b", "c"), "b")
    particles = np.array([[1.0, 2.0, 3.0, 4.0]])
    pos = layout.positions(particles)  # (2, N, M)
    np.testing.assert_array_equal(pos[:, :, 0].T, [[1.0, 2.0], [0.0, 0.0], [3.0, 4.0]])
    assert layout.columns("c") == slice(2, 4)
    with pytest.raises(KeyError):
        layout.index("z")


def test_range_likelihood_peaks_at_true_distance_and_is_robust() -> None:
    pos = np.zeros((2, 2, 3))  # (xy, robot, particle)
    pos[0, 1, :] = [1.0, 2.0, 3.0]  # three particles: robot 1 at x = 1, 2, 3
    batch = RangeBatch(
        np.array([0]),
        np.array([1]),
        np.array([2.3]),
        np.array([0.3]),
        np.array([0.1]),
        outlier_fraction=0.1,
        max_range=15.0,
    )
    ll = batch.log_likelihood(pos)
    assert np.argmax(ll) == 1
    # a wild outlier cannot push the log-likelihood below the uniform floor
    far = RangeBatch(
        np.array([0]), np.array([1]), np.array([50.0]), np.array([0.0]), np.array([0.1])
    )
    assert np.all(far.log_likelihood(pos) >= np.log(0.1 / 15.0) - 1e-9)


def test_relative_position_likelihood_peaks_at_measured_vector() -> None:
    pos = np.zeros((2, 2, 2))  # (xy, robot, particle)
    pos[:, 1, 0] = [1.0, 1.0]
    pos[:, 1, 1] = [1.0, -1.0]
    batch = RelativePositionBatch(
        np.array([0]), np.array([1]), np.array([[1.0, 1.0]]), np.array([0.1])
    )
    ll = batch.log_likelihood(pos)
    assert ll[0] > ll[1]


def test_odometry_motion_moves_by_relative_displacement() -> None:
    rng = np.random.default_rng(1)
    particles = np.zeros((20000, 4))
    disp = np.array([[0.5, 0.0], [1.0, 0.0], [0.0, 2.0]])  # robots a (ref), b, c
    sigma = np.array([0.0, 0.1, 0.0])
    OdometryMotion(process_noise=0.0).propagate(
        particles, np.array([1, 2]), 0, disp, sigma, 0.1, rng
    )
    np.testing.assert_allclose(particles.mean(axis=0), [0.5, 0.0, -0.5, 2.0], atol=0.01)
    assert particles[:, 0].std() == pytest.approx(0.1, rel=0.05)
    assert particles[:, 2].std() == pytest.approx(0.0, abs=1e-12)


def _triangle_loglik(truth: np.ndarray, sigma: float = 0.05):
    layout = StateLayout(("r", "a", "b"), "r")
    pairs = np.array([[0, 1], [0, 2], [1, 2]])
    full = np.vstack([[0.0, 0.0], truth])
    d = np.linalg.norm(full[pairs[:, 0]] - full[pairs[:, 1]], axis=1)
    robust = RangeBatch(pairs[:, 0], pairs[:, 1], d, np.zeros(3), np.full(3, sigma))
    gaussian = RangeBatch(
        pairs[:, 0], pairs[:, 1], d, np.zeros(3), np.full(3, sigma), outlier_fraction=0.0
    )
    return layout, robust.log_likelihood, gaussian.log_likelihood


def test_annealing_stopped_short_still_weighs_to_the_full_likelihood() -> None:
    """With one tempering stage allowed the particles follow ``L^beta`` (beta < 1): the final
    importance step must bring them to ``L`` (without it the median distance error is 2.9 m
    with one stage, 0.03 m with the full run; with it 0.10 m)."""
    truth = np.array([[2.0, 0.5], [0.5, 2.5]])
    layout, _, guide = _triangle_loglik(truth)
    pf = ParticleFilter(layout, 4000, (-4, 4, -4.5, 4.5), rng=np.random.default_rng(0))
    assert pf.initialize_annealed(guide, max_stages=1) == 1
    d_ra = np.linalg.norm(layout.positions(pf.particles).transpose(2, 1, 0)[:, 1], axis=1)
    assert np.median(np.abs(d_ra - np.linalg.norm(truth[0]))) < 0.25


def test_annealed_start_finds_the_formation_up_to_symmetry() -> None:
    truth = np.array([[2.0, 0.5], [0.5, 2.5]])
    layout, loglik, guide = _triangle_loglik(truth)
    pf = ParticleFilter(layout, 4000, (-4, 4, -4.5, 4.5), rng=np.random.default_rng(0))
    stages = pf.initialize_annealed(loglik, guide)
    assert stages > 1
    pos = layout.positions(pf.particles).transpose(2, 1, 0)  # (M, N, 2)
    # distances of every particle match the true ones (ranges fix the shape, not the rotation)
    d_ra = np.linalg.norm(pos[:, 1], axis=1)
    d_ab = np.linalg.norm(pos[:, 1] - pos[:, 2], axis=1)
    assert np.median(np.abs(d_ra - np.linalg.norm(truth[0]))) < 0.05
    assert np.median(np.abs(d_ab - np.linalg.norm(truth[0] - truth[1]))) < 0.05
    # spreading over rotations keeps the shape and spreads the bearing over the circle
    pf.spread_symmetries()
    pos = layout.positions(pf.particles).transpose(2, 1, 0)
    assert np.median(np.abs(np.linalg.norm(pos[:, 1], axis=1) - np.linalg.norm(truth[0]))) < 0.05
    bearings = np.arctan2(pos[:, 1, 1], pos[:, 1, 0])
    hist, _ = np.histogram(bearings, bins=8, range=(-np.pi, np.pi))
    assert hist.min() > 0.6 * hist.mean()


def test_resample_reinjects_prior_fraction() -> None:
    layout = StateLayout(("r", "a"), "r")
    pf = ParticleFilter(
        layout, 1000, (-4, 4, -4.5, 4.5), rng=np.random.default_rng(0), reinject_fraction=0.05
    )
    pf.particles[:] = 0.0
    pf.resample()
    moved = np.any(pf.particles != 0.0, axis=1).sum()
    assert moved == 50


def test_filter_rejects_bad_parameters() -> None:
    layout = StateLayout(("r", "a"), "r")
    with pytest.raises(ValueError):
        ParticleFilter(layout, 0, (-1, 1, -1, 1), rng=np.random.default_rng(0))
    with pytest.raises(ValueError):
        ParticleFilter(
            layout, 10, (-1, 1, -1, 1), rng=np.random.default_rng(0), resample="sometimes"
        )


def test_estimate_keeps_the_weighted_mean_and_publishes_the_ring_before_any_evidence() -> None:
    layout = StateLayout(("a", "b", "c"), "a")
    pf = ParticleFilter(layout, 3000, (-4, 4, -4.5, 4.5), rng=np.random.default_rng(0))
    pf.logw = log_normalize(np.log(np.random.default_rng(1).random(3000)))
    est = pf.estimate()
    w = np.exp(pf.logw)
    assert est.summary is not None and not est.summary.orientation_observable
    for k in range(2):
        x = pf.particles[:, 2 * k : 2 * k + 2]
        np.testing.assert_allclose(est.summary.weighted_mean[k], w @ x)
        # Nothing fused can tell the orientation: the moments of the posterior symmetrised
        # over rotations about the reference (mean there, E|p|^2 / 2 per axis).
        np.testing.assert_allclose(est.mean[k], 0.0)
        np.testing.assert_allclose(est.cov[k], 0.5 * (w @ np.sum(x * x, axis=1)) * np.eye(2))
    assert est.ess == pytest.approx(ess(pf.logw))


def test_estimate_is_the_weighted_mean_and_covariance_of_one_mode_once_resolved() -> None:
    layout = StateLayout(("a", "b", "c"), "a")
    pf = ParticleFilter(layout, 3000, (-4, 4, -4.5, 4.5), rng=np.random.default_rng(0))
    rng = np.random.default_rng(1)
    pf.particles[:] = np.array([2.0, 0.5, -1.0, 2.0]) + 0.1 * rng.standard_normal((3000, 4))
    pf.logw = log_normalize(np.log(rng.random(3000)))
    pf.evidence.moved(np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.0]]))
    est = pf.estimate()
    w = np.exp(pf.logw)
    assert est.summary is not None and est.summary.orientation_observable
    assert est.summary.n_modes == 1 and est.summary.mode_weight == pytest.approx(1.0, abs=1e-3)
    for k in range(2):
        x = pf.particles[:, 2 * k : 2 * k + 2]
        np.testing.assert_allclose(est.mean[k], w @ x)
        np.testing.assert_allclose(est.cov[k], np.cov(x.T, aweights=w, bias=True))


def test_robust_likelihood_matches_the_log_space_formula() -> None:
    rng = np.random.default_rng(2)
    pos = rng.normal(size=(2, 3, 50))
    batch = RangeBatch(
        np.array([0, 1]),
        np.array([1, 2]),
        np.array([1.0, 2.0]),
        np.array([0.2, 0.3]),
        np.array([0.1, 0.2]),
        outlier_fraction=0.1,
        max_range=15.0,
    )
    d = batch.predicted(pos)
    r = (batch.distance - batch.bias)[:, None] - d
    s = batch.sigma[:, None]
    gauss = np.exp(-0.5 * (r / s) ** 2) / (s * np.sqrt(2 * np.pi))
    expected = np.log(0.9 * gauss + 0.1 / 15.0).sum(axis=0)
    np.testing.assert_allclose(batch.log_likelihood(pos), expected)


@pytest.mark.parametrize(
    "model",
    [
        {},
        {"outlier_fraction": 0.0},
        {"outlier_fraction": 0.02, "nlos_fraction": 0.1},
        {"outlier_fraction": 0.0, "nlos_fraction": 0.1},
    ],
)
@pytest.mark.parametrize("arms", [False, True])
@pytest.mark.parametrize("m", [5, 3000])
def test_the_compiled_range_likelihood_is_the_numpy_one(
    model: dict[str, float], arms: bool, m: int
) -> None:
    """``add_log_likelihood`` (the particle filter's compiled pass) adds what
    ``log_likelihood`` gives, to round-off, with the reference in the middle of the team, tag
    offsets, far particles (``-inf`` where no floor holds them) and blocks of particles."""
    rng = np.random.default_rng(m)
    layout = StateLayout(("a", "b", "r", "c"), "r")
    ia, ib = (np.asarray(i, dtype=np.intp) for i in np.triu_indices(4, 1))
    batch = RangeBatch(
        ia,
        ib,
        rng.uniform(1.0, 6.0, 6),
        rng.normal(0.0, 0.1, 6),
        rng.uniform(0.05, 0.3, 6),
        arms=rng.normal(0.0, 0.2, (2, 6)) if arms else None,
        **model,
    )
    particles = rng.normal(0.0, 3.0, (m, 7))
    particles[0, :6] = 300.0  # far from every range
    with np.errstate(divide="ignore"):  # log(0) of the far particle without a floor
        want = batch.log_likelihood(layout.positions(particles), particles)
    got = np.full(m, 0.5)
    batch.add_log_likelihood(particles, layout, got)
    assert np.array_equal(np.isfinite(got), np.isfinite(want))
    finite = np.isfinite(want)
    np.testing.assert_allclose(got[finite], 0.5 + want[finite], rtol=1e-12, atol=1e-9)


def test_systematic_take_copies_the_rows_systematic_resample_picks() -> None:
    rng = np.random.default_rng(4)
    for m in (1, 7, 1000):
        w = rng.random(m) ** 4
        w[rng.random(m) < 0.3] = 0.0
        w[0] += 1e-3
        rows = rng.normal(size=(m, 3))
        u = np.random.default_rng(m).random()
        idx = systematic_resample(w / w.sum(), np.random.default_rng(m))
        out = np.empty_like(rows)
        systematic_take(w, u, rows, out)
        assert np.array_equal(out, rows[idx])


def test_renormalize_into_is_log_normalize_and_its_exp() -> None:
    logw = np.array([-3.0, np.nan, 2.0, -np.inf, np.inf, 0.5])
    want = log_normalize(np.where(np.isfinite(logw), logw, -np.inf))
    got, w = logw.copy(), np.empty(6)
    assert renormalize_into(got, w)
    np.testing.assert_allclose(got, want, rtol=1e-15)
    np.testing.assert_allclose(w, np.exp(want), rtol=1e-15)
    assert not renormalize_into(np.full(3, np.nan), np.empty(3))


@pytest.mark.parametrize("enabled", [False, True])
def test_both_steps_track_and_the_switch_picks_the_path(
    enabled: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``relloc.filter.compiled.ENABLED`` picks the compiled step or the NumPy one, read on
    every step; each tracks a moving triangle from the same converged cloud, and the NumPy
    predict draws from the filter's generator as it did before the compiled passes."""
    from relloc.filter import compiled

    if enabled and not compiled.AVAILABLE:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(compiled, "ENABLED", enabled)
    layout = StateLayout(("r", "a", "b"), "r")
    truth = np.array([[2.0, 0.5], [0.5, 2.5]])
    pf = ParticleFilter(layout, 2000, (-4, 4, -4.5, 4.5), rng=np.random.default_rng(1))
    pf.particles[:, :4] = truth.reshape(-1) + np.random.default_rng(2).normal(0, 0.3, (2000, 4))
    before = pf.particles.copy()
    disp = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, -0.1]])
    sigma = np.full(3, 0.01)
    rng = copy.deepcopy(pf.rng)
    pf.predict(disp, sigma, 0.1)
    if not enabled:  # the NumPy path: the generator's own normals, as drawn before
        want = before.copy()
        OdometryMotion()._propagate_numpy(
            want, np.array([1, 2]), 0, disp, sigma,
            np.sqrt(OdometryMotion().own_variance(sigma, [1, 2], 0.1)), rng, None,
        )  # fmt: skip
        np.testing.assert_array_equal(pf.particles[:, :4], want[:, :4])
    ia, ib = (np.asarray(i, dtype=np.intp) for i in np.triu_indices(3, 1))
    for step in range(20):
        truth = truth + disp[1:] - disp[0]
        full = np.vstack([[0.0, 0.0], truth])
        d = np.linalg.norm(full[ia] - full[ib], axis=1)
        batch = RangeBatch(ia, ib, d, np.zeros(3), np.full(3, 0.05))
        assert pf.update([batch])
        est = pf.estimate()
        pf.resample()
        if step < 19:
            pf.predict(disp, sigma, 0.1)
    assert np.linalg.norm(est.mean - truth, axis=1).max() < 0.3  # both within 0.15 m
