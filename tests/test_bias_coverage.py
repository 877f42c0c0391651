"""Bias coverage: the share of published 95 % bias intervals that hold the true bias, per pair
and over every pair, reported like the position coverage."""

from __future__ import annotations

import math

import pytest

from relloc.estimate import Estimate
from relloc.evaluation.selfcal_metrics import bias_coverage
from relloc.evaluation.selfcal_scores import BiasResult


def _estimates() -> list[Estimate]:
    # pair a-b: truth 0.30, estimates 0.30 +- 0.05 (covered); then 0.45 +- 0.05 (3 sigma off)
    # pair a-c: truth 0.20, always 0.25 +- 0.05 (1 sigma off: covered); before t=1 not scored
    out = []
    for t in range(10):
        ab = (0.30, 0.05) if t < 6 else (0.45, 0.05)
        out.append(Estimate(float(t), "pf", "r0", {}, biases={"a-b": ab, "a-c": (0.25, 0.05)}))
    return out


def test_the_coverage_counts_the_intervals_that_hold_the_truth() -> None:
    covered = bias_coverage(_estimates(), {"a-b": 0.30, "a-c": 0.20}, t_start=1.0)
    assert covered["a-b"].tolist() == [1.0] * 5 + [0.0] * 4
    assert covered["a-c"].tolist() == [1.0] * 9
    result = BiasResult({"a-b": (0.45, 0.05)}, {"a-b": 0.30}, {}, covered)
    assert result.coverage("a-b") == pytest.approx(5 / 9)
    assert result.coverage() == pytest.approx(14 / 18)
    assert math.isnan(result.coverage("x-y"))
    pairs = result.method_json()
    assert pairs["bias_coverage95"] == pytest.approx(14 / 18, abs=1e-5)
    assert pairs["pairs"]["a-b"]["bias_coverage95"] == pytest.approx(5 / 9, abs=1e-5)


def test_a_pair_without_a_truth_is_not_scored() -> None:
    assert bias_coverage(_estimates(), {"a-b": 0.30}, t_start=0.0).keys() == {"a-b"}
