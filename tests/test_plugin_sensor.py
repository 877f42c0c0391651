"""A sensor relloc has never heard of, added without changing a file under ``src``.

The toy fix (``tests/toy_sensor.py``: its own ``.msg``, event, measurement model and
descriptor; its topic in the team config's ``[sensors.toy_fix]`` table) is written with
odometry and UWB ranges of a simulated team into an MCAP bag with ``rosbags``, read back by the
bag source and fused by the particle filter, and replayed over Zenoh on loopback. The fixes
put one robot 0.5 m east of where it is: fused, they pull its estimate east.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from model_checks import assert_rows_are_the_log_likelihood_and_its_gradient
from toy_sensor import TOY, TOY_FIX, ToyFixBatch, ToyFixEvent
from waiting import wait_until

from relloc.config import ConfigError, TeamConfig
from relloc.engine import Engine
from relloc.estimate import Estimate
from relloc.evaluation.metrics import GroundTruth
from relloc.events import GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.filter import registry as models
from relloc.live import ReplayOptions, replay_bag, simulated_team
from relloc.live.publish import SIM_TIME_BASE, EventEncoder
from relloc.methods import build_pipeline
from relloc.ros.messages import typestore
from relloc.sensors import register, sensor_of, unregister
from relloc.sources.ingest import team_routes
from relloc.sources.rosbag import RosbagSource
from relloc.sources.zenoh_source import ZenohSource

TARGET = "r2"
PULL = 0.5
"""The fixes' error (m, +x): where the toy sensor says the target is, beyond the truth."""
SIGMA = 0.05
DURATION = 12.0
WARMUP = 6.0


@pytest.fixture
def toy() -> Iterator[None]:
    """The toy sensor registered for one test, unregistered afterwards."""
    register(TOY)
    try:
        yield
    finally:
        unregister(TOY)


def with_toy(config: TeamConfig) -> TeamConfig:
    table = {"topic": "/{robot}/toy_fix", "robots": [TARGET], "sigma": SIGMA}
    return dataclasses.replace(config, sensors={"toy_fix": table})


@pytest.fixture(scope="module")
def recording(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[Path, TeamConfig, GroundTruth, list[ToyFixEvent]]:
    """A simulated team's odometry, ranges and toy fixes (2 Hz, ``PULL`` m east of the truth)
    in an MCAP bag, encoded by the replay's encoder; the config (with the toy table), the
    ground truth and the fixes."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    sim, base_config = simulated_team(seed=0, duration=DURATION)
    config = with_toy(base_config.with_filter(particles=2000))
    events = list(sim.events())
    truth = GroundTruth(config.reference)
    for ev in events:
        if isinstance(ev, GroundTruthEvent):
            truth.add(ev)
    fixes = []
    for k in range(2, int(2 * DURATION)):
        t = 0.5 * k
        p, ref = truth.pose_at(TARGET, t), truth.pose_at(config.reference, t)
        assert p is not None and ref is not None
        fixes.append(ToyFixEvent(t, TARGET, p[0] - ref[0] + PULL, p[1] - ref[1], SIGMA))
    register(TOY)
    try:
        encoder = EventEncoder(config)
        data = sorted(
            (ev.t, i, ev)
            for i, ev in enumerate([*events, *fixes])
            if isinstance(ev, OdometryEvent | RangeEvent | ToyFixEvent)
        )
        bag = tmp_path_factory.mktemp("toy") / "toy_bag"
        with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            conns: dict[str, Any] = {}
            for t, _, ev in data:
                out = encoder.encode(ev, SIM_TIME_BASE)
                assert out is not None, ev
                channel, payload = out
                if channel.name not in conns:
                    conns[channel.name] = writer.add_connection(
                        channel.name, channel.msgtype, typestore=typestore()
                    )
                writer.write(conns[channel.name], round((t + SIM_TIME_BASE) * 1e9), payload)
    finally:
        unregister(TOY)
    return bag, config, truth, fixes


def run(bag: Path, config: TeamConfig) -> tuple[RosbagSource, list[Estimate], dict[str, int]]:
    source = RosbagSource(bag, config, ground_truth=False)
    pipeline = build_pipeline("pf", config, seed=0)
    Engine([pipeline]).run(source)
    return source, pipeline.estimates, dict(pipeline.localizer.stats)


def east_error(estimates: list[Estimate], truth: GroundTruth, reference: str) -> float:
    """Mean x error (m) of the target's estimate after the warm-up."""
    errors = []
    for e in estimates:
        if e.t - SIM_TIME_BASE < WARMUP:
            continue
        p, ref = (
            truth.pose_at(TARGET, e.t - SIM_TIME_BASE),
            truth.pose_at(reference, e.t - SIM_TIME_BASE),
        )
        assert p is not None and ref is not None
        errors.append(e.positions[TARGET][0] - (p[0] - ref[0]))
    assert len(errors) > 20
    return float(np.mean(errors))


def test_the_toy_sensor_is_decoded_counted_and_fused(toy: None, recording: Any) -> None:
    bag, config, truth, fixes = recording
    assert models.MODELS[ToyFixEvent] is ToyFixBatch and sensor_of(fixes[0]) is TOY
    routes = [r for r in team_routes(config) if r.kind == "toy_fix"]
    assert [(r.topic, r.robot, r.msgtypes) for r in routes] == [("/r2/toy_fix", TARGET, (TOY_FIX,))]

    source, fused, stats = run(bag, config)
    assert source.topics["/r2/toy_fix"] == "toy_fix"
    assert source.stats.events["toy_fix"] == len(fixes) == 22
    decoded = [e for e in source if isinstance(e, ToyFixEvent)]
    assert np.allclose(
        [(e.t - SIM_TIME_BASE, e.x, e.y, e.sigma) for e in decoded],
        [(f.t, f.x, f.y, f.sigma) for f in fixes],
        atol=1e-6,
    )
    assert stats["toy_fix"] == len(fixes)  # every fix accepted, counted under the model's stat

    unregister(TOY)  # the same bag without the plug-in (and without its table)
    plain_config = dataclasses.replace(config, sensors={})
    plain_source, plain, plain_stats = run(bag, plain_config)
    assert "toy_fix" not in plain_source.stats.events and "toy_fix" not in plain_stats
    register(TOY)

    pulled, without = (
        east_error(fused, truth, config.reference),
        east_error(plain, truth, config.reference),
    )
    assert abs(without) < 0.15
    assert pulled > 0.25 and pulled - without > 0.25  # towards the fixes' +0.5 m


def test_an_unknown_plug_in_or_a_bad_table_is_a_config_error(toy: None) -> None:
    _, config = simulated_team(seed=0, duration=2.0)
    good = with_toy(config)
    assert TeamConfig.from_dict(good.to_dict()) == good  # the table survives a round trip
    assert "[sensors.toy_fix]" in good.to_toml()
    with pytest.raises(ConfigError, match=r"sensors\.toy_fix\.sigma"):
        team_routes(
            dataclasses.replace(config, sensors={"toy_fix": {"topic": "/{robot}/t", "sigma": -1.0}})
        )
    with pytest.raises(ConfigError, match=r"sensors\.range: this sensor takes no table"):
        team_routes(dataclasses.replace(config, sensors={"range": {}}))
    unregister(TOY)
    with pytest.raises(
        ConfigError, match=r"sensors\.toy_fix: no sensor plug-in of that name is registered"
    ):
        team_routes(good)
    register(TOY)


def test_the_toy_sensor_replays_over_zenoh(
    toy: None, recording: Any, sessions: tuple[Any, Any]
) -> None:
    bag, config, _, fixes = recording
    server, client = sessions
    source = ZenohSource(config)
    assert "r2/toy_fix" in source.keys
    source.attach(server)
    got: list[Any] = []
    try:
        stats = replay_bag(bag, config, client, ReplayOptions(rate=8.0, wait=5.0))
        assert stats.per_key["r2/toy_fix"] == len(fixes)

        def all_toy_fixes() -> bool:
            got.extend(a.event for a in source.take_queued())
            return sum(isinstance(e, ToyFixEvent) for e in got) >= len(fixes)

        assert wait_until(all_toy_fixes, timeout=20.0)
    finally:
        source.detach()
    toy_fixes = [e for e in got if isinstance(e, ToyFixEvent)]
    assert np.allclose(
        [(e.t - SIM_TIME_BASE, e.x, e.y) for e in toy_fixes],
        [(f.t, f.x, f.y) for f in fixes],
        atol=1e-6,
    )
    assert source.stats.events["toy_fix"] == len(fixes)
    assert not source.stats.rejected


def test_the_toy_models_rows_are_its_log_likelihood_and_its_gradient(toy: None) -> None:
    """The check every built-in model passes (``test_measurement_models``), for the toy."""
    from relloc.filter.measurement import ModelContext
    from relloc.filter.state import StateLayout

    _, config = simulated_team(seed=0, duration=2.0)
    layout = StateLayout(config.robot_names, config.reference)
    fixes = [ToyFixEvent(0.0, "r2", 1.0, -2.0, 0.2), ToyFixEvent(0.0, "r4", -0.5, 0.7, 0.3)]
    (model,) = ToyFixBatch.build(fixes, ModelContext(with_toy(config), layout))
    x = np.random.default_rng(0).normal(0.0, 2.0, (4, layout.width))
    assert_rows_are_the_log_likelihood_and_its_gradient(model, layout, x)


def test_the_simulator_runs_the_toy_sensors_hook(toy: None) -> None:
    """A registered plug-in adds its events to a simulation; the simulator's own are unchanged."""
    sim, config = simulated_team(seed=0, duration=5.0)
    sim.config = with_toy(config)  # the team as configured with the toy sensor
    with_fixes = list(sim.advance(2.0)) + list(sim.advance(5.0))  # cut into steps: the same ticks
    unregister(TOY)
    plain, _ = simulated_team(seed=0, duration=5.0)
    register(TOY)
    fixes = [e for e in with_fixes if isinstance(e, ToyFixEvent)]
    assert [e.t for e in fixes] == [0.5 * k for k in range(1, 11)]
    for e in fixes:
        x, y, _ = sim.true_pose(TARGET, e.t)
        rx, ry, _ = sim.true_pose(config.reference, e.t)
        assert (e.robot, e.x, e.y, e.sigma) == (TARGET, x - rx, y - ry, SIGMA)
    assert [e for e in with_fixes if not isinstance(e, ToyFixEvent)] == list(plain.events())


@pytest.mark.parametrize("kind", ["particle", "gaussian_sum", "range_graph", "smoother"])
def test_the_toy_sensor_reaches_every_kind(toy: None, recording: Any, kind: str) -> None:
    """One model serves every estimator: the particle likelihood, the Gaussian sums' linear
    rows and the smoother's factors (``ToyFixBatch.fixes``) all pull the target towards the
    fixes. (The fixes contradict the ranges by ten of their sigmas: the smoother's watchdog
    restarts on it, so only its oriented estimates are scored.)"""
    bag, config, truth, fixes = recording
    _, fused, stats = run(bag, config.with_filter(kind=kind))
    assert stats["toy_fix"] == len(fixes)
    assert stats.get("smoother_toy_fix_unused", 0) == 0
    errors = []
    for e in fused:
        t = e.t - SIM_TIME_BASE
        p, ref = truth.pose_at(TARGET, t), truth.pose_at(config.reference, t)
        if t >= WARMUP and e.orientation_observable and p is not None and ref is not None:
            errors.append(e.positions[TARGET][0] - (p[0] - ref[0]))
    assert len(errors) >= 5
    assert float(np.mean(errors)) > 0.25


def test_a_kind_that_takes_no_factors_of_a_sensor_says_so_and_counts_it(
    toy: None, recording: Any, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    bag, config, _, fixes = recording
    monkeypatch.delattr(ToyFixBatch, "fixes")  # a plug-in written for the filters only
    with caplog.at_level("WARNING"):
        _, _, stats = run(bag, config.with_filter(kind="smoother"))
    assert "the smoother uses no toy_fix measurements" in caplog.text
    assert stats["smoother_toy_fix_unused"] == len(fixes)
