"""``[filter] kind`` names the filter that runs as ``pf``: each kind runs the localizer it names,
``auto`` picks as the modes and the team size call for, a kind that cannot do what the modes
ask is a :class:`ConfigError`, and the run header says which filter ran."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from test_rosbag_source import synthetic_messages, synthetic_team

from relloc import estimators
from relloc.cli import main
from relloc.config import ConfigError, TeamConfig
from relloc.engine import Engine
from relloc.estimators.gaussian_sum.localizer import SelfCalibratingLocalizer
from relloc.estimators.particle.localizer import ParticleFilterLocalizer
from relloc.estimators.range_graph.localizer import RangeGraphLocalizer
from relloc.estimators.smoother import LARGE_TEAM_ROBOTS
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.methods import build_pipeline, filter_choice, filter_header, filter_kind
from relloc.simulator import multi_scenario
from relloc.simulator.scenarios import grid_scenario

SMALL = {"particles": 2000, "selfcal_particles": 200, "selfcal_init_particles": 2000}


def _run(config: TeamConfig, duration: float = 15.0) -> tuple[type, dict[str, float], np.ndarray]:
    """The localizer class of ``pf``, its APE medians after 5 s and its last estimate."""
    sim = multi_scenario(seed=0, duration=duration)
    pipeline = build_pipeline("pf", config, seed=0)
    gt = GroundTruth(config.reference)
    engine = Engine([pipeline], truth_sinks=[gt.add])
    engine.run(sim.events())
    report = evaluate(engine, gt, "multi", 5.0).methods["pf"]
    last = pipeline.estimates[-1]
    return (
        type(pipeline.localizer),
        {r: s.median for r, s in report.robots.items()},
        np.array(last.positions["r1"]),
    )


@pytest.mark.parametrize(
    ("kind", "localizer"),
    [
        ("particle", ParticleFilterLocalizer),
        ("gaussian_sum", SelfCalibratingLocalizer),
        ("range_graph", RangeGraphLocalizer),
    ],
)
def test_each_kind_runs_the_filter_it_names(kind: str, localizer: type) -> None:
    config = multi_scenario(seed=0, duration=15.0).config.with_filter(kind=kind, **SMALL)
    ran, ape, _ = _run(config)
    assert ran is localizer and filter_kind(config) == kind
    assert set(ape) == {"r1", "r2", "r3", "r4"} and max(ape.values()) < 0.2


def test_auto_picks_as_before() -> None:
    """The default (``auto``) runs exactly what ``particle`` runs on a small compass team, the
    Gaussian sum where headings or scales are estimated, the smoother on a large team."""
    config = multi_scenario(seed=0, duration=15.0).config.with_filter(**SMALL)
    assert config.filter.kind == "auto" and filter_kind(config) == "particle"
    auto, ape_auto, last_auto = _run(config, 8.0)
    particle, ape_particle, last_particle = _run(config.with_filter(kind="particle"), 8.0)
    assert auto is particle is ParticleFilterLocalizer
    assert ape_auto == ape_particle and np.array_equal(last_auto, last_particle)
    assert filter_kind(config.with_modes(heading="estimate")) == "gaussian_sum"
    assert filter_kind(config.with_modes(odom_scale="online")) == "gaussian_sum"
    assert filter_kind(config.with_modes(bias="online")) == "particle"
    large = grid_scenario(0, robots=LARGE_TEAM_ROBOTS, duration=2.0).config
    assert filter_kind(large) == "smoother"
    assert filter_kind(large.with_modes(bias="online")) == "particle"
    assert (
        filter_kind(grid_scenario(0, robots=LARGE_TEAM_ROBOTS - 1, duration=2.0).config)
        == "particle"
    )


def test_auto_gives_robots_without_odometry_the_smoother() -> None:
    """A robot without ``odom_topic`` is a ranges-only robot: the smoother's motion prior (the
    smoother estimates online biases too)."""
    config = multi_scenario(seed=0, duration=1.0).config
    assert filter_choice(config) == ("particle", "5 robots with odometry")
    tag = config.with_robot("r3", odom_topic="")
    assert filter_choice(tag) == ("smoother", "1 of 5 robots without odometry")
    assert filter_choice(tag.with_modes(bias="online")) == (
        "smoother",
        "1 of 5 robots without odometry, biases online",
    )
    assert filter_choice(tag.with_modes(heading="estimate")) == (
        "gaussian_sum",
        "headings estimated",
    )
    assert filter_choice(tag.with_filter(kind="particle")) == ("particle", "the config's")
    assert (
        filter_header(["pf"], tag)
        == 'filter: smoother (kind "auto": 1 of 5 robots without odometry)'
    )


@pytest.mark.parametrize(
    ("kind", "modes", "message"),
    [
        ("particle", {"heading": "estimate"}, "'particle' cannot estimate the headings"),
        ("particle", {"odom_scale": "online"}, "'particle' cannot estimate the odometry scales"),
        ("range_graph", {"heading": "estimate"}, "'range_graph' cannot estimate the headings"),
        (
            "range_graph",
            {"bias": "online"},
            "'range_graph' cannot estimate the range biases online",
        ),
    ],
)
def test_a_kind_that_cannot_do_what_the_modes_ask_is_a_config_error(
    kind: str, modes: dict[str, str], message: str
) -> None:
    config = multi_scenario(seed=0, duration=1.0).config
    with pytest.raises(ConfigError, match=message):
        estimators.check(config.with_filter(kind=kind).with_modes(**modes))
    with pytest.raises(ConfigError, match=message):
        build_pipeline("pf", config.with_modes(**modes).with_filter(kind=kind))
    raw = {
        **config.to_dict(),
        "filter": {
            "kind": kind,
            "self_calibration": {
                {"heading": "heading_mode", "odom_scale": "odom_scale_mode", "bias": "bias_mode"}[
                    k
                ]: v
                for k, v in modes.items()
            },
        },
    }
    with pytest.raises(ConfigError, match=message):
        filter_kind(TeamConfig.from_dict(raw))
    # the Gaussian sum does all of it
    assert (
        filter_kind(config.with_filter(kind="gaussian_sum").with_modes(**modes)) == "gaussian_sum"
    )


def test_the_run_header_names_the_filter(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = multi_scenario(seed=0, duration=1.0).config
    assert filter_header(["multilateration"], config) is None
    assert (
        filter_header(["multilateration", "pf_uv"], config)
        == 'filter: particle (kind "auto": 5 robots with odometry)'
    )
    assert (
        filter_header(["pf"], config.with_modes(heading="estimate"))
        == 'filter: gaussian_sum (kind "auto": headings estimated)'
    )
    path = tmp_path / "demo.json"
    main(
        [
            "demo",
            "--seed",
            "0",
            "--scenarios",
            "single",
            "--particles",
            "500",
            "--no-progress",
            "--json",
            str(path),
        ]
    )
    out = capsys.readouterr().out
    assert 'single: filter: particle (kind "auto": 2 robots with odometry)' in out
    assert json.loads(path.read_text())["scenarios"]["single"]["methods"]["pf"]["robots"]


def test_the_run_header_of_a_recording_names_the_filter(
    tmp_path: Path, bag_writer: Callable[..., Path], capsys: pytest.CaptureFixture[str]
) -> None:
    bag = bag_writer(tmp_path / "synthetic", synthetic_messages())
    config = tmp_path / "team.toml"
    synthetic_team().with_filter(
        particles=300, kind="gaussian_sum", selfcal_particles=50, selfcal_init_particles=300
    ).save(config)
    args = [
        "run",
        str(bag),
        "--config",
        str(config),
        "--methods",
        "pf",
        "--warmup",
        "0.5",
        "--no-progress",
    ]
    assert main([*args, "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert 'synthetic: filter: gaussian_sum (kind "gaussian_sum")' in out
    assert out.index("synthetic: filter:") < out.index("APE after 0.5 s warm-up")
    # --filter-kind overrides the config's kind, for a recording and for the demo.
    assert main([*args, "--out", str(tmp_path / "out"), "--filter-kind", "particle"]) == 0
    assert 'synthetic: filter: particle (kind "particle")' in capsys.readouterr().out
    demo = [
        "demo",
        "--scenarios",
        "single",
        "--particles",
        "300",
        "--methods",
        "pf",
        "--no-progress",
    ]
    assert main([*demo, "--out", str(tmp_path / "demo"), "--filter-kind", "gaussian_sum"]) == 0
    assert 'single: filter: gaussian_sum (kind "gaussian_sum")' in capsys.readouterr().out


def test_an_unknown_kind_is_a_config_error_naming_the_registered_ones() -> None:
    config = multi_scenario(seed=0, duration=1.0).config.with_filter(kind="kalman")
    message = "filter.kind = 'kalman': expected one of auto, "
    with pytest.raises(ConfigError, match=message) as raised:
        estimators.check(config)
    for name in ("particle", "gaussian_sum", "range_graph", "smoother"):
        assert name in str(raised.value)
    with pytest.raises(ConfigError, match=message):
        build_pipeline("pf", config)
