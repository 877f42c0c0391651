"""What a run's figures mean: the convergence time's definition, the table's caption, the plots'
panels. Synthetic errors, no filter run."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from relloc.evaluation.metrics import ApeStats, Paired, convergence_time
from relloc.evaluation.plots import plot_ape, plot_ape_over_time, plot_trajectories, robot_colors
from relloc.evaluation.report import MethodReport, ScenarioReport, print_table
from relloc.evaluation.scores import ApeResult, AteResult, ConvergenceResult

T = np.round(np.arange(0.0, 60.0, 0.1), 6)


def _paired(errors: np.ndarray, t: np.ndarray = T) -> Paired:
    n = len(t)
    gt = np.zeros((n, 2))
    est = np.c_[errors, np.zeros(n)]
    return Paired(t, est, gt, np.ones(n))


def test_a_bad_first_second_is_not_converged_at_zero() -> None:
    """Robot b is 4 m off for the first second (one lucky estimate at 0.3 s): converged after
    1.0 s, not 0.0 s (the first second is under 5 % of a minute, which a tail-only count let
    pass) and not 0.3 s (the worst-robot APE must hold under 0.3 m for a second)."""
    good = np.full(T.size, 0.1)
    bad_start = np.where(T < 1.0, 4.0, 0.1)
    bad_start[3] = 0.1
    assert convergence_time({"a": _paired(good), "b": _paired(bad_start)}) == pytest.approx(1.0)
    assert convergence_time({"a": _paired(good)}, start=-2.0) == pytest.approx(2.0)


def test_convergence_tolerates_five_percent_and_needs_a_rest() -> None:
    errors = np.full(T.size, 0.1)
    errors[100::25] = 1.0  # 4 % of the estimates after 10 s, isolated
    assert convergence_time({"a": _paired(errors)}) == pytest.approx(0.0)
    errors = np.full(T.size, 0.1)
    errors[100:400:5] = 1.0  # two bad estimates a second from 10 s to 40 s: converged after them
    assert convergence_time({"a": _paired(errors)}) == pytest.approx(39.6)
    late = np.full(T.size, 1.0)
    late[-5:] = 0.1  # good only in the last half second: never
    assert math.isnan(convergence_time({"a": _paired(late)}))


def _report(with_empty: bool = True) -> ScenarioReport:
    rng = np.random.default_rng(0)
    robots = {f"r{k}": _paired(np.abs(rng.normal(0.1, 0.05, T.size))) for k in range(1, 4)}
    methods = {
        "pf": MethodReport(
            {
                "ape": ApeResult(
                    {r: ApeStats.of(p.errors[p.t >= 10.0]) for r, p in robots.items()}
                ),
                "ate": AteResult(
                    {r: 0.05 for r in robots}, {r: len(p.t) for r, p in robots.items()}
                ),
                "convergence": ConvergenceResult(convergence_time(robots)),
            },
            paired=robots,
        )
    }
    if with_empty:
        empty = {r: _paired(np.zeros(0), np.zeros(0)) for r in robots}
        methods["multilateration"] = MethodReport(
            {
                "ape": ApeResult({r: ApeStats.of(np.zeros(0)) for r in robots}),
                "ate": AteResult({}),
                "convergence": ConvergenceResult(math.nan),
            },
            paired=empty,
        )
    return ScenarioReport(
        "toy", 10.0, 60.0, methods, 0.0, reference="r0", truth_name="ground truth"
    )


def test_table_names_the_reference_and_defines_converged_after() -> None:
    console = Console(record=True, width=140)
    print_table(_report(), console)
    text = " ".join(console.export_text().split())  # captions wrap with the table's width
    assert "positions relative to r0" in text
    assert "converged after: seconds from the start of the run" in text
    assert "under 0.3 m for 1 s and for 95 % of the rest of the run" in text
    assert "no estimate" in text and "never" in text


def test_plots_are_written_with_an_empty_method(tmp_path: Path) -> None:
    report = _report()
    for plot in (plot_trajectories, plot_ape, plot_ape_over_time):
        path = plot(report, tmp_path / f"{plot.__name__}.png")
        assert path.stat().st_size > 10_000


def test_robot_colours_differ_within_a_panel() -> None:
    for n in (2, 10, 12):
        colours = robot_colors([f"r{k}" for k in range(n)])
        assert len(set(colours.values())) == n
