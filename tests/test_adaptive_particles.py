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
from relloc.estimators.particle.filter import ParticleFilter
from relloc.estimators.particle.localizer import ParticleFilterLocalizer, count_rule
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.events import GroundTruthEvent
from relloc.faults import Faults, inject
from relloc.filter.adaptive import KldSampling, kld_bound, occupied_cells
from relloc.filter.state import StateLayout
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
        layout,
        n,
        (-5.0, 5.0, -5.0, 5.0),
        rng=np.random.default_rng(0),
        count_rule=rule,
        reinject_fraction=0.0,
    )
    pf.particles = pf.rng.normal(0.0, 0.03, (n, 4)) + np.array([2.0, 0.0, 0.0, 2.0])
    pf.evidence.moved(
        np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]])
    )  # motion: the orientation can be resolved
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
    minimum after convergence, the restart (the watchdog's, or the divergence monitor's)
    re-anneals at the full count, and it falls again once the filter has recovered."""
    sim = multi_scenario(seed=0, duration=25.0)
    faults = Faults(kidnap=(("r2", 15.0, 2.0, 0.0),))
    ests, loc = _sim_run(sim, 6000, 1000, faults)
    t0 = ests[0].t
    counts = np.array([e.particles for e in ests])
    t = np.array([e.t - t0 for e in ests])
    assert counts[0] == 6000
    before = counts[(t > 8.0) & (t < 14.0)]
    assert before.max() < 6000 and np.median(before) <= 2000
    counters = loc.fault_counters()
    assert counters["divergence_detected"] + counters["inconsistency_restarts"] >= 1
    flagged = np.array([e.recovering or e.inconsistent for e in ests])
    first = int(np.flatnonzero(flagged)[0])
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
    assert all(
        later[0] > earlier[0] for earlier, later in zip(p["series"], p["series"][1:], strict=False)
    )
    assert p["final"] == engine.pipelines[0].estimates[-1].particles


def test_the_adaptive_keys_are_validated() -> None:
    fc = FilterConfig.from_dict({"adaptive": {"min_particles": 3000, "mc_tolerance": 0.009}})
    assert fc.adaptive.min_particles == 3000 and fc.adaptive.mc_tolerance == 0.009
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
    # what became a constant says so, and the rule's defaults are those constants
    with pytest.raises(
        ConfigError,
        match=r"kld_bin is no longer a setting: it is the constant relloc\.filter\.adaptive\.KLD_BIN",
    ):
        FilterConfig.from_dict({"adaptive": {"kld_bin": 0.2}})
    assert (KldSampling(1, 2).epsilon, KldSampling(1, 2).quantile, KldSampling(1, 2).bin_size) == (
        0.05,
        0.99,
        0.2,
    )
    # min_particles above the full count caps at it; a pair (no orientation kernel) has its own
    # floor; "fixed" turns the rule off.
    sim = multi_scenario(seed=0, duration=1.0)
    config = sim.config.with_filter(particles=1500)
    team = StateLayout(config.robot_names, config.reference)
    assert count_rule(config, team) == KldSampling(1500, 1500, mc_tolerance=0.007)
    with pytest.raises(ConfigError, match="mc_tolerance_ordered is no longer a setting"):
        config.with_filter(mc_tolerance_ordered=0.012)
    big = config.with_filter(particles=30_000)
    assert count_rule(big, team).min_particles == 2000
    pair = StateLayout(config.robot_names[:2], config.robot_names[0])
    assert count_rule(big, pair).min_particles == 5000
    no_kernel = big.with_filter(rotation_kernel=0.0)
    assert count_rule(no_kernel, team).min_particles == 5000
    fixed = dataclasses.replace(config, filter=config.filter.with_changes(particle_count="fixed"))
    assert count_rule(fixed, team) is None
