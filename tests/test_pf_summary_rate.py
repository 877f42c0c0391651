"""The particle filter's summary at the rate it is used, and its predict's noise: the moments
and modes every step, the shape and distances only where read; the compiled summary is the
NumPy one to round-off, the compiled predict's noise the motion model's."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import relloc.estimators.particle.filter as pf_module
from relloc.estimators.particle.localizer import ParticleFilterLocalizer
from relloc.filter.motion import OdometryMotion, standard_normal
from relloc.filter.summary import DeferredSummary, summarize, summarize_particles
from relloc.simulator import multi_scenario


@pytest.mark.parametrize(
    ("width", "k", "sigma_ref"), [(8, 4, 0.02), (10, 4, 0.02), (8, 4, 0.0), (2, 1, 0.1)]
)
def test_predict_moves_by_the_odometry_with_the_noise_model_and_is_reproducible(
    width: int, k: int, sigma_ref: float
) -> None:
    """The compiled predict (its own normals, seeded from the filter's generator): the mean
    move is the odometry's relative displacement, each coordinate's variance its own plus the
    reference's, shared between robots (the same axis) and not between axes; further columns
    untouched; the same generator state gives the same particles."""
    data = np.random.default_rng(5)
    m = 200_000
    particles = np.repeat(data.normal(size=(1, width)), m, axis=0)
    disp = data.normal(size=(k + 1, 2))
    sigma = np.abs(data.normal(size=k + 1)) * 0.1 + 0.01
    sigma[0] = sigma_ref
    others = np.arange(1, k + 1)
    motion = OdometryMotion()
    got = particles.copy()
    motion.propagate(got, others, 0, disp, sigma, 0.1, np.random.default_rng(3))
    again = particles.copy()
    motion.propagate(again, others, 0, disp, sigma, 0.1, np.random.default_rng(3))
    assert np.array_equal(got, again)
    moved = got[:, : 2 * k] - particles[:, : 2 * k]
    own = np.repeat(motion.own_variance(sigma, others, 0.1), 2)
    np.testing.assert_allclose(
        moved.mean(axis=0), (disp[others] - disp[0]).reshape(-1), atol=4 * np.sqrt(own.max() / m)
    )
    cov = np.cov(moved, rowvar=False).reshape(2 * k, 2 * k)
    expected = np.diag(own) + sigma_ref**2 * np.kron(np.ones((k, k)), np.eye(2))
    np.testing.assert_allclose(cov, expected, atol=5 * expected.max() * np.sqrt(2 / m))
    assert np.array_equal(got[:, 2 * k :], particles[:, 2 * k :])


def test_the_compiled_normals_are_standard_normal() -> None:
    from scipy import stats

    x = standard_normal(11, 1_000_000)
    assert abs(x.mean()) < 5e-3 and abs(x.var() - 1.0) < 5e-3
    assert abs(stats.skew(x)) < 1e-2 and abs(stats.kurtosis(x)) < 2e-2
    assert stats.kstest(x, "norm").pvalue > 1e-3
    assert np.mean(np.abs(x) > 3.6541528853610088) == pytest.approx(
        2 * stats.norm.sf(3.6541528853610088), rel=0.1
    )  # the ziggurat's tail


def _two_modes(m: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    formation = np.array([[2.0, 0.5], [-1.0, 2.0], [0.5, -1.5]])
    theta = np.where(rng.random(m) < 0.7, 0.3, 2.0) + 0.05 * rng.standard_normal(m)
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    x, y = formation[None, :, 0], formation[None, :, 1]
    rel = np.stack([c * x - s * y, s * x + c * y], axis=-1) + 0.05 * rng.standard_normal((m, 3, 2))
    return rel, rng.random(m)


@pytest.mark.parametrize("m", [300, 5000])
@pytest.mark.parametrize("can_resolve", [True, False])
def test_a_deferred_summary_computes_only_what_is_read_and_equals_the_eager_one(
    m: int, can_resolve: bool
) -> None:
    rel, w = _two_modes(m, seed=m)
    eager = summarize(rel, w, can_resolve=can_resolve, floor=0.01)
    lazy = summarize(rel, w, can_resolve=can_resolve, floor=0.01, deferred=True)
    assert isinstance(lazy, DeferredSummary) and type(eager) is not DeferredSummary
    assert lazy.computed == frozenset()
    for name in ("mean", "cov", "weighted_mean", "members"):
        assert np.array_equal(getattr(lazy, name), getattr(eager, name))
    assert (lazy.mode_weight, lazy.n_modes, lazy.orientation_std, lazy.orientation_observable) == (
        eager.mode_weight,
        eager.n_modes,
        eager.orientation_std,
        eager.orientation_observable,
    )
    assert lazy.computed == frozenset()
    assert np.array_equal(lazy.distances, eager.distances)
    assert lazy.computed == {"distances"}
    assert np.array_equal(lazy.shape, eager.shape) and np.array_equal(
        lazy.shape_cov, eager.shape_cov
    )
    assert lazy.computed == {"shape", "distances"}


@pytest.mark.parametrize("m", [7, 300, 5000])
@pytest.mark.parametrize("can_resolve", [True, False])
@pytest.mark.parametrize("k", [1, 3])
def test_the_compiled_particle_summary_is_the_summary_to_round_off(
    m: int, can_resolve: bool, k: int
) -> None:
    """:func:`summarize_particles` over particle rows (bias columns after the positions) is
    :func:`summarize` of the same formations, deferred or not: two orientation modes, one of
    them partly mirrored."""
    rel, w = _two_modes(m, seed=m + k)
    rel = rel[:, :k].copy()
    rel[: m // 5, :, 1] *= -1.0
    rows = np.concatenate([rel.reshape(m, 2 * k), np.ones((m, 2))], axis=1)
    want = summarize(rel, w, can_resolve=can_resolve, floor=0.01)
    for deferred in (False, True):
        got = summarize_particles(
            rows, k, w, can_resolve=can_resolve, floor=0.01, deferred=deferred
        )
        assert np.array_equal(got.members, want.members)
        assert (got.n_modes, got.orientation_observable) == (
            want.n_modes,
            want.orientation_observable,
        )
        for name in ("mean", "cov", "weighted_mean", "mode_weight", "orientation_std"):
            np.testing.assert_allclose(getattr(got, name), getattr(want, name), atol=1e-10)
        for name in ("shape", "shape_cov", "distances"):
            np.testing.assert_allclose(getattr(got, name), getattr(want, name), atol=1e-10)


def _run(
    monkeypatch: pytest.MonkeyPatch, deferred: bool
) -> tuple[list[str], list[tuple[bool, frozenset[str]]]]:
    """Published estimates (reprs) of a short run with one estimate per 0.2 s (half the steps
    unpublished) and, per step, whether it published and what of its summary was computed."""
    if not deferred:
        eager = summarize_particles

        def forced(*args: Any, **kwargs: Any) -> Any:
            kwargs["deferred"] = False
            return eager(*args, **kwargs)

        monkeypatch.setattr(pf_module, "summarize_particles", forced)
    sim = multi_scenario(seed=1, duration=8.0)
    loc = ParticleFilterLocalizer(sim.config.with_filter(particles=600), seed=1)
    loc.estimate_period = 0.2
    steps: list[tuple[bool, frozenset[str]]] = []
    run_batch = loc._run_batch

    def watched() -> list[Any]:
        out = run_batch()
        s = loc.filter.last_summary
        if loc.initialized and isinstance(s, DeferredSummary):
            steps.append((bool(out), s.computed))
        return out

    monkeypatch.setattr(loc, "_run_batch", watched)
    published = [repr(e) for ev in sim.events() for e in loc.process(ev)]
    return published, steps


def test_only_published_steps_compute_the_shape_and_publish_what_the_eager_summary_did(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    lazy, steps = _run(monkeypatch, deferred=True)
    assert len(lazy) > 20
    unpublished = [computed for shown, computed in steps if not shown]
    published = [computed for shown, computed in steps if shown]
    assert len(unpublished) > 10 and len(published) > 10
    assert all("shape" not in computed for computed in unpublished)
    assert all("shape" in computed for computed in published)
    with monkeypatch.context() as patch:
        eager, _ = _run(patch, deferred=False)
    assert lazy == eager


def test_without_a_consumer_of_the_shape_it_is_left_out_and_nothing_else_changes() -> None:
    """``shape_wanted`` False (a live server whose shape key nobody subscribes to): where the
    orientation is observable the shape is neither computed nor carried and the distances are
    left out of the estimate (where it is not, the shape is what is published, so it is
    computed); every other field, and the filter's path, are what they were."""
    sim = multi_scenario(seed=2, duration=8.0)
    runs = []
    for wanted in (True, False):
        loc = ParticleFilterLocalizer(sim.config.with_filter(particles=600), seed=2)
        loc.shape_wanted = wanted
        computed: list[frozenset[str]] = []
        out = []
        for ev in sim.events():
            for e in loc.process(ev):
                out.append(e)
                s = loc.filter.last_summary
                computed.append(
                    s.computed
                    if isinstance(s, DeferredSummary)
                    else frozenset({"shape", "distances"})
                )
        runs.append((out, computed))
    (full, full_computed), (lean, lean_computed) = runs
    assert len(full) == len(lean) > 20
    seen = [e.orientation_observable for e in lean]
    assert any(seen) and not all(seen)  # the start is a ring, then motion resolves it
    assert all(e.shape and e.distances for e in full)
    assert all(
        bool(e.shape) != o and bool(e.distances) != o for e, o in zip(lean, seen, strict=True)
    )
    assert all("shape" in c for c in full_computed)
    assert all(("shape" in c) != o for c, o in zip(lean_computed, seen, strict=True))
    for a, b in zip(full, lean, strict=True):
        assert (a.t, a.positions, a.covariances, a.ess, a.mode_weight, a.n_modes) == (
            b.t,
            b.positions,
            b.covariances,
            b.ess,
            b.mode_weight,
            b.n_modes,
        )
