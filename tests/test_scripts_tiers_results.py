"""``scripts/tiers_results.py``: the table of docs/results/tiers.md from synthetic per-seed reports
(no recording is run)."""

from __future__ import annotations

import math
from types import ModuleType, SimpleNamespace

from load_file import ROOT, load_module

SCRIPT = ROOT / "scripts" / "tiers_results.py"


def _script() -> ModuleType:
    return load_module(SCRIPT, "tiers_results")


def _report(medians: dict[str, dict[str, float]]) -> SimpleNamespace:
    """What ``run_recording`` reports, reduced to what the table reads: per method each robot's
    APE median and RMSE (twice the median here) and the mean of the medians."""
    methods = {}
    for method, robots in medians.items():
        finite = [v for v in robots.values() if math.isfinite(v)]
        methods[method] = SimpleNamespace(
            robots={r: SimpleNamespace(median=v, rmse=2 * v) for r, v in robots.items()},
            mean_ape_median=sum(finite) / len(finite) if finite else math.nan,
        )
    return SimpleNamespace(methods=methods)


def test_the_table_of_seeds() -> None:
    tr = _script()
    per_seed = [
        _report({"pf": {"b": 0.2, "a": 0.1}, "multilateration": {"a": math.nan, "b": 0.3}}),
        _report({"pf": {"b": 0.4, "a": 0.3}, "multilateration": {"a": math.nan, "b": 0.5}}),
        _report({"pf": {"b": 0.6, "a": math.nan}, "multilateration": {"a": math.nan, "b": 0.4}}),
    ]
    lines = tr.table({"bag": per_seed}).splitlines()
    assert lines[:2] == list(tr.HEADER)
    assert lines[2:] == [
        "| bag | pf | a | 0.100 | 0.200 | 0.200 | 0.100–0.300 |",
        "| bag | pf | b | 0.200 | 0.400 | 0.400 | 0.200–0.600 |",
        "| bag | pf | **mean** | 0.150 | | 0.350 | 0.150–0.600 |",
        "| bag | multilateration | a | – | – | – | – |",
        "| bag | multilateration | b | 0.300 | 0.600 | 0.400 | 0.300–0.500 |",
        "| bag | multilateration | **mean** | 0.300 | | 0.400 | 0.300–0.500 |",
    ]


def test_recordings_follow_one_another_under_one_header() -> None:
    tr = _script()
    one = [_report({"pf": {"a": 0.1}})]
    text = tr.table({"x": one, "y": one})
    assert text.endswith("\n")
    assert [line.split(" | ")[0] for line in text.splitlines()[2:]] == ["| x"] * 2 + ["| y"] * 2
