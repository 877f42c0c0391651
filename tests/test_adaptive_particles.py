"""The adaptive particle count (:mod:`relloc.filter.adaptive`): the KLD bound, the filter's
resampling to a new size, and the sampled localizer on simulated runs (shrinks once converged,
full while the orientation is unobservable, back to full after a divergence); its keys, and the
count in the estimates and ``--json``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from relloc.config import ConfigError, FilterConfig
from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.events import GroundTruthEvent
from relloc.faults import Faults, inject
from relloc.filter.adaptive import KldSampling, kld_bound, occupied_cells
from relloc.filter.pf import ParticleFilter
from relloc.filter.resampling import systematic_resample
from relloc.filter.state import StateLayout
from relloc.localizers.sampled import ParticleFilterLocalizer, count_rule
from relloc.methods import build_pipeline
from relloc.simulator import multi_scenario
from relloc.simulator.scenarios import static_scenario


def test_the_kld_bound_grows_with_the_occupied_cells() -> None:
    z = 2.3263478740408408  # the 0.99 normal quantile
    assert kld_bound(1, 0.05, z) == 1
    # Fox's bound, by hand: (k - 1) / (2 eps) * (1 - a + sqrt(a) z)^3 with a = 2 / (9 (k - 1)).
    a = 2.0 / (9.0 * 99)
    assert kld_bound(100, 0.05, z) == int(np.ceil(99 / 0.1 * (1 - a + np.sqrt(a) * z) ** 3))
    assert kld_bound(100, 0.05, z) < kld_bound(1000, 0.05, z) < kld_bound(1000, 0.01, z)
    rule = KldSampling(100, 50_000)
    assert rule.z == pytest.approx(z)


def test_occupied_cells_counts_the_distinct_grid_cells() -> None:
    pts = np.array([[0.01, 0.01], [0.05, 0.15], [0.25, 0.0], [-0.05, 0.0], [0.01, 0.02]])
    assert occupied_cells(pts, 0.2) == 3  # (0, 0) x3, (1, 0), (-1, 0)
    rng = np.random.default_rng(0)
    wide = rng.uniform(-5, 5, (4000, 6))
    assert occupied_cells(wide, 0.2) == 4000  # in 6 dimensions every particle has its own cell


def test_the_rule_keeps_the_full_count_while_wide_and_clamps_a_narrow_posterior() -> None:
    rule = KldSampling(1000, 20_000, mc_tolerance=0.007)
    rng = np.random.default_rng(1)
    narrow = rng.normal(0.0, 0.02, (5000, 6)) + 3.0
    assert rule.size(narrow, wide=True) == 20_000
    assert rule.size(narrow, wide=False) == 1000  # a few cells: the minimum
    # A posterior spread 0.3 m along one direction needs sigma^2 / (0.5 tol^2) particles for
    # the Monte Carlo error of its mean.
    assert rule.size(narrow, wide=False, sigma=0.3) == int(np.ceil(0.09 / (0.5 * 0.007**2)))
    # Every kept particle in its own cell: the bound asks for ~10x as many (growth).
    spread = rng.uniform(-5, 5, (1500, 6))
    assert rule.size(spread, wide=False) > 10_000
    with pytest.raises(ValueError):
        KldSampling(3000, 2000)


def _ring_filter(n: int, rule: KldSampling | None) -> ParticleFilter:
    layout = StateLayout(("r", "a", "b"), "r")
    pf = ParticleFilter(
        layout, n, (-5.0, 5.0, -5.0, 5.0), rng=np.random.default_rng(0), count_rule=rule, reinject_fraction=0.0
    )
    pf.particles = pf.rng.normal(0.0, 0.03, (n, 4)) + np.array([2.0, 0.0, 0.0, 2.0])
    pf.evidence.moved(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]]))  # motion: the orientation can be resolved
    return pf


def test_the_filter_resamples_to_the_rules_size_and_back_to_full_on_recovery() -> None:
    rule = KldSampling(500, 8000)
    pf = _ring_filter(8000, rule)
    pf.resample()
    assert pf.n == 8000  # no summary yet: wide
    pf.estimate()
    assert pf.last_summary is not None and pf.last_summary.orientation_observable
    pf.resample()
    assert pf.n == 500 and pf.particles.shape == (500, 4) and pf.logw.shape == (500,)
    assert np.isclose(np.exp(pf.logw).sum(), 1.0)
    assert pf.estimate().particles == 500
    slots = pf.inject(np.tile([2.0, 0.0, 0.0, 2.0], (100, 1)))
    assert pf.n == 8000 and pf.particles.shape[0] == 8000
    assert slots.size == 1600  # the injected share (100 of 500) kept at the full count
    assert np.allclose(pf.particles[slots], [2.0, 0.0, 0.0, 2.0])
    # A fixed-count filter never changes size.
    fixed = _ring_filter(3000, None)
    fixed.estimate()
    fixed.resample()
    assert fixed.n == 3000


def test_an_annealed_start_restarts_at_the_full_count() -> None:
    rule = KldSampling(500, 6000)
    pf = _ring_filter(6000, rule)
    pf.estimate()
    pf.resample()
    assert pf.n == 500

    def loglik(pos: np.ndarray, _: np.ndarray) -> np.ndarray:
        d = np.hypot(pos[0, 1], pos[1, 1])  # robot a 2 m from the reference
        return -0.5 * ((d - 2.0) / 0.1) ** 2

    pf.initialize_annealed(loglik)
    assert pf.n == 6000 and pf.particles.shape[0] == 6000 and pf.last_summary is None


def _sim_run(sim, particles: int, min_particles: int, faults: Faults | None = None):
    config = sim.config.with_filter(particles=particles, min_particles=min_particles)
    loc = ParticleFilterLocalizer(config, seed=0)
    events = sim.events() if faults is None else inject(sim.events(), faults)
    ests = []
    for ev in events:
        if not isinstance(ev, GroundTruthEvent):
            ests += loc.process(ev)
    return ests + loc.flush(), loc


def test_the_count_shrinks_once_converged_and_grows_back_after_a_divergence() -> None:
    """Five simulated robots, r2 moved 2 m unseen at 15 s: the count falls from 6000 to the
    minimum after convergence, the divergence monitor's re-annealed start puts it back to the
    full count, and it falls again once the filter has recovered."""
    sim = multi_scenario(seed=0, duration=25.0)
    faults = Faults(kidnap=(("r2", 15.0, 2.0, 0.0),))
    ests, loc = _sim_run(sim, 6000, 1000, faults)
    t0 = ests[0].t
    counts = np.array([e.particles for e in ests])
    t = np.array([e.t - t0 for e in ests])
    assert counts[0] == 6000
    before = counts[(t > 8.0) & (t < 15.0)]
    assert before.max() < 6000 and np.median(before) <= 2000
    assert loc.stats["divergence_detected"] >= 1
    recovering = np.array([e.recovering for e in ests])
    first = int(np.flatnonzero(recovering)[0])
    assert counts[first] == 6000  # re-annealed at the full count
    assert counts[-1] < 6000  # and narrow again at the end


def test_the_count_stays_full_while_the_orientation_is_unobservable() -> None:
    ests, loc = _sim_run(static_scenario(seed=1, duration=10.0), 3000, 500)
    assert len(ests) > 60 and not any(e.orientation_observable for e in ests)
    assert {e.particles for e in ests} == {3000}
    assert loc.stats["resampled"] > 0  # it did resample, at the full count


def test_the_count_is_in_the_json_report() -> None:
    sim = multi_scenario(seed=1, duration=14.0)
    config = sim.config.with_filter(particles=5000, min_particles=1000)
    gt = GroundTruth(config.reference)
    engine = Engine([build_pipeline("pf", config, seed=1)], truth_sinks=[gt.add]).run(sim.events())
    out = evaluate(engine, gt, "multi", warmup=5.0).methods["pf"].to_json()
    p = out["particles"]
    assert p["max"] == 5000 and p["series"][0][1] == 5000
    assert p["final"] < 5000 and p["median_after_warmup"] < 5000
    assert all(later[0] > earlier[0] for earlier, later in zip(p["series"], p["series"][1:], strict=False))
    assert p["final"] == engine.pipelines[0].estimates[-1].particles


def test_the_adaptive_keys_are_validated() -> None:
    fc = FilterConfig.from_dict({"adaptive": {"min_particles": 3000, "kld_epsilon": 0.02}})
    assert fc.adaptive.min_particles == 3000 and fc.adaptive.kld_epsilon == 0.02
    assert FilterConfig.section_of("mc_tolerance") == "adaptive"
    for bad in (
        {"min_particles": 0},
        {"min_particles_no_kernel": 0},
        {"kld_epsilon": 0.0},
        {"kld_bin": -0.1},
        {"kld_quantile": 1.0},
        {"mc_tolerance": -1.0},
        {"mc_tolerance_ordered": -0.01},
        {"particle_count": "ess"},
        {"min_particle": 10},
    ):
        with pytest.raises(ConfigError, match=r"filter\.adaptive"):
            FilterConfig.from_dict({"adaptive": bad})
    # min_particles above the full count caps at it; a pair (no orientation kernel) has its own
    # floor; "fixed" turns the rule off.
    sim = multi_scenario(seed=0, duration=1.0)
    config = sim.config.with_filter(particles=1500)
    team = StateLayout(config.robot_names, config.reference)
    assert count_rule(config, team) == KldSampling(1500, 1500, mc_tolerance=0.007)
    ordered = config.with_filter(mc_tolerance_ordered=0.012)
    assert count_rule(ordered, team) == KldSampling(1500, 1500, mc_tolerance=0.007, mc_tolerance_ordered=0.012)
    big = config.with_filter(particles=30_000)
    assert count_rule(big, team).min_particles == 2000
    pair = StateLayout(config.robot_names[:2], config.robot_names[0])
    assert count_rule(big, pair).min_particles == 5000
    no_kernel = big.with_filter(rotation_kernel=0.0)
    assert count_rule(no_kernel, team).min_particles == 5000
    fixed = dataclasses.replace(config, filter=config.filter.with_changes(particle_count="fixed"))
    assert count_rule(fixed, team) is None


def test_ordered_systematic_resampling_keeps_the_weighted_mean_along_the_order() -> None:
    """Walking the particles sorted by a coordinate, the systematic draw takes the quantiles
    of the weighted sample along it: the mean of the copies misses the weighted mean by
    O(spread / M) instead of O(spread / sqrt(M)) in stored order; every particle is still
    copied floor or ceil of M w times."""
    rng = np.random.default_rng(3)
    m = 2000
    x = rng.normal(0.0, 0.5, m)
    w = rng.random(m)
    w /= w.sum()
    target = float(w @ x)
    plain, ordered = [], []
    for _ in range(50):
        plain.append(abs(x[systematic_resample(w, rng)].mean() - target))
        idx = systematic_resample(w, rng, order=np.argsort(x))
        ordered.append(abs(x[idx].mean() - target))
        assert np.all(np.abs(np.bincount(idx, minlength=m) - m * w) < 1.0)
    assert np.median(plain) == pytest.approx(0.00289, abs=1e-5)  # 0.5 / sqrt(2000) = 0.011 at most
    assert np.median(ordered) == pytest.approx(0.00052, abs=1e-5)
    assert max(ordered) < 0.001 < max(plain)


def _wide_cloud(rule: KldSampling | None, seed: int) -> ParticleFilter:
    """A formation 0.5 m wide along its orientation (0.25 rad at 2 m) and 0.03 m across, with
    uneven weights."""
    pf = _ring_filter(3000, rule)
    pf.rotate(pf.rng.normal(0.0, 0.25, 3000))
    lw = np.log(pf.rng.uniform(0.5, 1.5, 3000))
    pf.logw = lw - np.log(np.exp(lw).sum())
    pf.estimate()  # one observable mode: the count rule may act
    pf.rng = np.random.default_rng(100 + seed)
    return pf


def test_an_adaptive_filter_resamples_along_its_widest_direction() -> None:
    """With a count rule the resampling walks the cloud along its principal axis (here the
    orientation): the resampled mean stays within 0.6 mm of the weighted mean; a fixed-count
    filter (stored order) moves it by 1.4-5.5 mm (20 resamplings each)."""
    errors: dict[str, list[float]] = {}
    ordered_rule = KldSampling(3000, 3000, mc_tolerance=0.007, mc_tolerance_ordered=0.012)
    for label, rule in (("ordered", ordered_rule), ("stored", None)):
        for k in range(20):
            pf = _wide_cloud(rule, k)
            before = np.exp(pf.logw) @ pf.particles
            pf.resample()
            errors.setdefault(label, []).append(float(np.abs(pf.particles.mean(axis=0) - before).max()))
    assert np.median(errors["ordered"]) == pytest.approx(0.00047, abs=1e-5)
    assert max(errors["ordered"]) < 0.00065
    assert np.median(errors["stored"]) == pytest.approx(0.00321, abs=1e-5)
    assert min(errors["stored"]) > 0.0014


def test_the_kernel_of_an_adaptive_filter_keeps_the_orientations_mean_exactly() -> None:
    """The Liu-West turn of every particle it moves: with a count rule its mean is zero to
    round-off (moment-matched noise); with a fixed count it is the noise's sample mean."""
    means = {}
    for label, rule in (("adaptive", KldSampling(4000, 4000)), ("fixed", None)):
        pf = _ring_filter(4000, rule)
        pf.rotate(pf.rng.normal(0.0, 0.1, 4000))
        pf._ordered = rule is not None  # as after an ordered resampling
        turns: list[np.ndarray] = []
        rotate = pf.rotate
        pf.rotate = lambda t, rotate=rotate, turns=turns: (turns.append(t.copy()), rotate(t))[1]  # type: ignore[method-assign]
        assert pf.rejuvenate_rotation(0.1)
        moved = turns[0] != 0.0
        assert moved.sum() == 4000
        means[label] = float(turns[0][moved].mean())
    assert abs(means["adaptive"]) < 1e-15
    assert means["fixed"] == pytest.approx(-0.000376, abs=1e-6)  # about sqrt(0.1) 0.1 / sqrt(4000)


def test_the_floor_of_an_ordered_resampling_counts_what_the_order_leaves() -> None:
    """Along the principal axis the ordered draw leaves (0.007 / 0.01)^2 = 0.49 of the
    variance to the Monte Carlo floor, across it all: a cloud 0.5 m wide along its orientation
    (robots 2 m out, 0.25 rad) and 0.03 m across is sized for about 0.35 m instead of its
    published 0.5 m, half the particles; without ``mc_tolerance_ordered`` the draw keeps the
    stored order and the floor the published spread; a pair is never ordered."""
    rule = KldSampling(500, 20_000, mc_tolerance=0.007, mc_tolerance_ordered=0.01)
    assert rule.ordered_share == pytest.approx(0.49)
    assert KldSampling(500, 20_000, mc_tolerance=0.007).ordered_share == 1.0
    pf = _ring_filter(20_000, rule)
    pf.rotate(pf.rng.normal(0.0, 0.25, 20_000))
    pf.estimate()
    published = pf.widest_std()
    pf.resample()
    assert pf._ordered
    assert published == pytest.approx(0.4860, abs=1e-4)
    assert pf._ordered_sigma == pytest.approx(0.3406, abs=1e-4)  # about sqrt(0.49) 0.4860
    assert pf.n == rule.monte_carlo_bound(pf._ordered_sigma) == 4734
    assert rule.monte_carlo_bound(published) == 9642
    plain = _ring_filter(20_000, KldSampling(500, 20_000, mc_tolerance=0.007))  # no allowance: stored order
    plain.rotate(plain.rng.normal(0.0, 0.25, 20_000))
    plain.estimate()
    plain.resample()
    assert not plain._ordered and plain.n == rule.monte_carlo_bound(plain.widest_std()) > 4734
    layout = StateLayout(("r", "a"), "r")
    pair = ParticleFilter(layout, 20_000, (-5.0, 5.0, -5.0, 5.0), rng=np.random.default_rng(0), count_rule=rule)
    pair.particles = pair.rng.normal(0.0, 0.3, (20_000, 2)) + np.array([2.0, 0.0])
    pair.evidence.moved(np.array([[0.0, 0.0], [1.0, 0.0]]))
    pair.estimate()
    assert not pair.posterior_wide and pair._resampling_order(np.full(20_000, 1.0 / 20_000)) is None
