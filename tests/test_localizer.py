"""The localizer on simulated runs: convergence from the uniform prior, and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from relloc.engine import Engine
from relloc.estimators.particle.localizer import ParticleFilterLocalizer
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.events import (
    GroundTruthEvent,
    HeightEvent,
    OdometryEvent,
    RangeEvent,
    RelativeObservation,
)
from relloc.filter.measurement import ModelContext
from relloc.filter.ranges import NLOS_FRACTION, RangeBatch
from relloc.filter.state import StateLayout
from relloc.localizers.multilateration import MultilaterationLocalizer
from relloc.methods import build_pipeline
from relloc.simulator import multi_scenario, single_scenario


def _run(sim, methods, particles, seed=0):
    config = sim.config.with_filter(particles=particles)
    gt = GroundTruth(config.reference)
    engine = Engine([build_pipeline(m, config, seed=seed) for m in methods], truth_sinks=[gt.add])
    engine.run(sim.events())
    return engine, gt


def test_pf_converges_on_simulated_multi_robot_run() -> None:
    sim = multi_scenario(seed=1, duration=30.0)
    engine, gt = _run(sim, ["pf", "multilateration"], particles=8000, seed=1)
    report = evaluate(engine, gt, "multi", warmup=10.0)
    pf = report.methods["pf"]
    for robot, stats in pf.robots.items():
        assert stats.n > 150, robot
        assert stats.median < 0.2, (robot, stats)
    assert pf.convergence_s < 10.0
    # the particle filter beats multilateration with one alignment per run
    assert pf.mean_ape_median < report.methods["multilateration"].mean_ape_median


def test_pf_converges_with_a_single_range() -> None:
    sim = single_scenario(seed=2, duration=30.0)
    engine, gt = _run(sim, ["pf", "multilateration"], particles=5000, seed=2)
    report = evaluate(engine, gt, "single", warmup=10.0)
    assert report.methods["pf"].robots["r1"].median < 0.25
    # multilateration honestly has no estimate from one range
    assert report.methods["multilateration"].robots["r1"].n == 0
    assert engine.pipelines[1].localizer.stats["no_estimate"] > 0


def test_initial_estimate_is_not_from_ground_truth() -> None:
    """Before enough ranges arrive there is no estimate, and the first one is spread wide."""
    sim = multi_scenario(seed=3, duration=3.0)
    config = sim.config.with_filter(particles=2000)
    loc = ParticleFilterLocalizer(config, seed=0)
    first = None
    for ev in sim.events():
        if isinstance(ev, GroundTruthEvent):
            continue
        out = loc.process(ev)
        if out and first is None:
            first = out[0]
    assert first is not None
    # right after the annealed start the formation's rotation is unknown: wide covariance
    assert max(first.std(r) for r in first.positions) > 1.0


def _team_localizer(**filter_changes):
    sim = single_scenario(seed=0, duration=5.0)
    config = sim.config.with_filter(particles=500, **filter_changes)
    return sim, ParticleFilterLocalizer(config, seed=0)


@pytest.mark.parametrize("distance", [math.nan, -0.5, math.inf, 1e6])
def test_invalid_ranges_are_rejected_and_counted(distance: float) -> None:
    _, loc = _team_localizer()
    assert loc.process(RangeEvent(1.0, "r0", "r1", distance, "n_0", "n_1")) == []
    assert loc.rejected == {"invalid_range": 1}


def test_unknown_robots_and_bad_odometry_are_rejected_and_counted() -> None:
    _, loc = _team_localizer()
    loc.process(RangeEvent(1.0, "r0", "ghost", 2.0))
    loc.process(OdometryEvent(1.0, "ghost", 0.0, 0.0, 0.0))
    loc.process(OdometryEvent(1.0, "r1", math.nan, 0.0, 0.0))
    loc.process(OdometryEvent(1.0, "r1", 0.0, 0.0, 0.0, z=math.inf))
    loc.process(HeightEvent(1.0, "r1", 1.2))  # a 2D filter has no height: ignored, counted
    loc.process(RelativeObservation(1.0, "r0", "r1", (1.0, math.nan), 0.1))
    loc.process(RangeEvent(1.0, "r1", "r1", 2.0))
    assert loc.rejected == {
        "unknown_robot": 2,
        "invalid_odometry": 2,
        "invalid_relative_observation": 1,
        "self_range": 1,
    }
    assert loc.stats["ignored_HeightEvent"] == 1


def test_time_going_backwards_is_rejected_and_counted_without_crash() -> None:
    sim, loc = _team_localizer()
    events = [ev for ev in sim.events() if not isinstance(ev, GroundTruthEvent)]
    estimates = []
    for ev in events:
        estimates += loc.process(ev)
    n_before = len(estimates)
    assert n_before > 0
    # an odometry message from the past, and a range older than what was already fused
    assert loc.process(OdometryEvent(0.5, "r1", 0.0, 0.0, 0.0)) == []
    assert loc.process(RangeEvent(0.5, "r0", "r1", 2.0, "n_0", "n_1")) == []
    assert loc.rejected["out_of_order_odometry"] == 1
    assert loc.rejected["late_measurement"] == 1
    # the filter goes on: a later range is accepted and fused
    t = events[-1].t + 1.0
    loc.process(RangeEvent(t, "r0", "r1", 2.0, "n_0", "n_1"))
    out = loc.process(RangeEvent(t + 0.5, "r0", "r1", 2.01, "n_0", "n_1"))
    assert out and np.isfinite(out[0].positions["r1"]).all()


def test_repeated_range_values_are_not_fused_twice() -> None:
    _, loc = _team_localizer()
    loc.process(RangeEvent(1.0, "r0", "r1", 2.0, "n_0", "n_1"))
    loc.process(RangeEvent(1.1, "r0", "r1", 2.0, "n_0", "n_1"))
    assert loc.rejected == {"repeated_range": 1}


def test_multilateration_rejects_the_same_bad_input() -> None:
    sim = single_scenario(seed=0, duration=5.0)
    loc = MultilaterationLocalizer(sim.config)
    loc.process(RangeEvent(1.0, "r0", "r1", math.nan))
    assert loc.rejected == {"invalid_range": 1}


def _feed(loc, events):
    out = []
    for ev in events:
        if not isinstance(ev, GroundTruthEvent):
            out += loc.process(ev)
    return out


def test_one_far_future_stamp_is_rejected_and_does_not_freeze_the_filter() -> None:
    """A corrupted stamp (a range or an odometry message 1e6 s ahead) is rejected as a time
    jump; the filter goes on emitting estimates and every robot keeps its odometry."""
    sim, loc = _team_localizer()
    events = [e for e in sim.events() if not isinstance(e, GroundTruthEvent)]
    half = len(events) // 2
    before = _feed(loc, events[:half])
    t = events[half].t
    assert loc.process(RangeEvent(t + 1e6, "r0", "r1", 2.0, "n_0", "n_1")) == []
    assert loc.process(OdometryEvent(t + 1e6, "r1", 0.0, 0.0, 0.0)) == []
    after = _feed(loc, events[half:])
    assert loc.rejected.get("time_jump") == 2
    assert len(after) >= 0.8 * len(before) * (len(events) - half) / half
    assert max(e.t for e in after) < t + 10.0
    assert "out_of_order_odometry" not in loc.rejected


def test_a_real_gap_costs_two_events_then_the_clock_jumps() -> None:
    """The first events set the clock by their median; a gap of the whole stream (two
    robots agree) costs two events, then the clock follows it."""
    _, loc = _team_localizer()
    for k in range(5):
        loc.process(OdometryEvent(1.0 + 0.1 * k, "r0" if k % 2 else "r1", 0.0, 0.0, 0.0))
    loc.process(OdometryEvent(100.0, "r0", 0.0, 0.0, 0.0))
    loc.process(OdometryEvent(100.1, "r1", 0.0, 0.0, 0.0))
    assert loc.rejected == {"time_jump": 2}
    loc.process(OdometryEvent(100.2, "r0", 0.0, 0.0, 0.0))
    loc.process(OdometryEvent(100.3, "r1", 0.0, 0.0, 0.0))
    assert loc.rejected == {"time_jump": 2}
    assert loc.stats["odometry"] == 7 and loc.stats["clock_jumps_followed"] == 1


def test_a_measurement_older_than_the_fused_batch_is_late_and_time_never_goes_back() -> None:
    sim, loc = _team_localizer()
    _feed(loc, sim.events())
    loc.flush()
    t = loc.t
    assert loc.process(RangeEvent(t - 0.01, "r0", "r1", 2.0, "n_0", "n_1")) == []
    loc.flush()
    assert loc.rejected.get("late_measurement") == 1
    assert loc.t == t and loc.last_estimate is not None and loc.last_estimate.t <= t


def test_an_estimate_per_batch_despite_jittered_batch_times() -> None:
    """Three pairs ranging at 10 Hz with 10 ms of jitter: batches on the 0.1 s grid, stamped
    with their newest range, give an estimate every 0.1 s on average (not about 7 Hz), never
    two within half a period."""
    from relloc.config import RobotConfig, TeamConfig

    config = TeamConfig(tuple(RobotConfig(r, uwb_node=f"n{i}") for i, r in enumerate("abc")), "a")
    loc = MultilaterationLocalizer(config)
    where = {"a": (0.0, 0.0), "b": (3.0, 0.0), "c": (0.0, 2.0)}
    rng = np.random.default_rng(0)
    events = []
    for x, y in (("a", "b"), ("a", "c"), ("b", "c")):
        for t in np.arange(rng.uniform(0.0, 0.1), 20.0, 0.1) + rng.normal(0.0, 0.01, 200):
            events.append(
                RangeEvent(float(t), x, y, math.dist(where[x], where[y]) + rng.normal(0.0, 0.01))
            )
    estimates = _feed(loc, sorted(events, key=lambda e: e.t))
    times = np.array([e.t for e in estimates])
    assert len(times) >= 0.97 * 200
    assert np.min(np.diff(times)) >= 0.05 - 1e-9


def test_online_bias_rejects_a_node_pair_it_has_no_state_for() -> None:
    sim = single_scenario(seed=0, duration=5.0)
    config = sim.config.with_filter(particles=500, bias_mode="online")
    loc = ParticleFilterLocalizer(config, seed=0)
    _feed(loc, sim.events())
    assert loc.process(RangeEvent(loc.t + 0.5, "r0", "r1", 3.3, "n_9", "n_1")) == []
    assert loc.rejected.get("unknown_node_pair") == 1
    loc.flush()


def test_self_observations_and_non_numbers_are_rejected() -> None:
    _, loc = _team_localizer()
    loc.process(RelativeObservation(1.0, "r0", "r0", (1.0, 0.0), 0.1))
    loc.process(RangeEvent(1.0, "r0", "r1", "2.0", "n_0", "n_1"))  # type: ignore[arg-type]
    loc.process(RangeEvent(1.0, "r0", "r1", 0.0, "n_0", "n_1"))
    loc.process("hello")  # type: ignore[arg-type]
    assert loc.rejected == {"self_observation": 1, "invalid_range": 2, "unknown_event_type": 1}


def test_a_calibrated_range_scale_is_applied_to_range_bias_and_sigma() -> None:
    """``measured = scale * true + bias``: every consumer sees ``(measured - bias) / scale``."""
    from dataclasses import replace

    from relloc.config import PairCalibration

    sim = single_scenario(seed=0, duration=5.0)
    uwb = replace(
        sim.config.uwb, pairs={"n_0-n_1": PairCalibration(bias=0.3, scale=1.1, sigma=0.11)}
    )
    config = replace(sim.config, uwb=uwb)
    layout = StateLayout(config.robot_names, config.reference)
    event = RangeEvent(1.0, "r0", "r1", 5.8, "n_0", "n_1")
    for range_model in ("symmetric", "nlos"):  # the NLOS model's line-of-sight sigma too
        (model,) = RangeBatch.build([event], ModelContext(config, layout, range_model=range_model))
        assert isinstance(model, RangeBatch)
        assert (model.distance - model.bias)[0] == pytest.approx((5.8 - 0.3) / 1.1)
        assert model.sigma[0] == pytest.approx(0.11 / 1.1)
        assert model.nlos_fraction == (NLOS_FRACTION if range_model == "nlos" else 0.0)
