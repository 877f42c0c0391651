"""Estimator kinds are plug-ins: a kind defined in one module outside ``src`` (``toy_kind``)
is run by ``pf``, chosen by ``auto`` where it suits, refused where it cannot do what the modes
ask, offered by ``--filter-kind`` and listed in the capability table; the built-in kinds'
registrations say what each can do."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import pytest

from relloc import estimators
from relloc.config import ConfigError
from relloc.engine import Engine
from relloc.estimators.registry import capability_table
from relloc.methods import build_pipeline, filter_choice
from relloc.simulator import multi_scenario


@pytest.fixture
def toy() -> Iterator[estimators.Kind]:
    import toy_kind

    estimators.register(toy_kind.KIND)
    yield toy_kind.KIND
    estimators.unregister(toy_kind.KIND.name)


def test_a_kind_of_ones_own_runs_as_pf(toy: estimators.Kind) -> None:
    scenario = multi_scenario(seed=0, duration=3.0)
    config = scenario.config.with_filter(kind=toy.name)
    pipeline = build_pipeline("pf", config)
    assert type(pipeline.localizer).__name__ == "LastRangeLocalizer"
    Engine([pipeline]).run(scenario.events())
    estimates = pipeline.estimates
    assert len(estimates) > 10
    last = estimates[-1]
    assert set(last.positions) <= set(config.robot_names) - {config.reference}
    assert all(p[1] == 0.0 and p[0] > 0.0 for p in last.positions.values())


def test_auto_picks_a_kind_of_ones_own_where_it_suits(toy: estimators.Kind) -> None:
    config = multi_scenario(seed=0, duration=1.0).config
    assert filter_choice(config) == ("particle", f"{len(config.robots)} robots with odometry")
    line = dataclasses.replace(config, name="line")
    assert filter_choice(line) == ("last_range", "a team in a line")
    # it estimates no headings: with headings estimated, the Gaussian sum is picked
    assert filter_choice(line.with_modes(heading="estimate"))[0] == "gaussian_sum"
    with pytest.raises(ConfigError, match="'last_range' cannot estimate the headings"):
        estimators.check(line.with_filter(kind="last_range").with_modes(heading="estimate"))


def test_the_command_line_and_the_table_offer_a_kind_of_ones_own(toy: estimators.Kind) -> None:
    from relloc.cli import build_parser

    assert "last_range" in estimators.names()
    run = build_parser().parse_args(
        ["run", "BAG", "--config", "c.toml", "--filter-kind", "last_range"]
    )
    assert run.filter_kind == "last_range"
    row = next(line for line in capability_table().splitlines() if "`last_range`" in line)
    assert "each robot at its last range" in row


def test_unregistered_it_is_gone() -> None:
    assert "last_range" not in estimators.names()
    assert set(estimators.names()) == {
        "auto",
        "particle",
        "gaussian_sum",
        "range_graph",
        "smoother",
        "smoother3d",
    }


@pytest.mark.parametrize(
    ("kind", "headings", "online_biases", "smoothed"),
    [
        ("particle", False, True, False),
        ("gaussian_sum", True, True, False),
        ("range_graph", False, False, False),
        ("smoother", False, True, True),
    ],
)
def test_the_built_in_kinds_say_what_they_can_do(
    kind: str, headings: bool, online_biases: bool, smoothed: bool
) -> None:
    caps = estimators.get(kind).capabilities
    assert (caps.headings, caps.online_biases, caps.smoothed, caps.dimensions) == (
        headings,
        online_biases,
        smoothed,
        (2,),
    )
    assert hasattr(estimators.get(kind).load(), "smoothed_estimates") == smoothed
