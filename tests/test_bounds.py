"""Heading bounds: a heading that both estimates know may turn as fast as its walk allows."""

from __future__ import annotations

import math

import numpy as np

from relloc.config import RobotConfig, TeamConfig
from relloc.filter.base import FilterEstimate
from relloc.localizers.bounds import CalibrationBounds

TEAM = TeamConfig((RobotConfig("r0"), RobotConfig("r1")), reference="r0").with_filter(
    heading_walk=0.04, reference_heading_walk=0.04
)


def _fe(heading: float, spread: float) -> FilterEstimate:
    return FilterEstimate(
        np.zeros((1, 2)),
        np.eye(2)[None],
        1.0,
        headings={"r0": (0.0, 0.01), "r1": (heading, spread)},
    )


def test_a_known_heading_may_turn_with_its_walk_not_faster() -> None:
    bounds = CalibrationBounds(TEAM, {})
    # 0.04 rad/sqrt(s) over 10 s with spreads of 0.05: 5 sigma is 0.72 rad (42 deg)
    for k in range(11):
        assert bounds.violation(_fe(0.06 * k, 0.05), t=float(k)) is None  # 0.6 rad in 10 s
    bounds = CalibrationBounds(TEAM, {})
    for k in range(10):
        assert bounds.violation(_fe(0.0, 0.05), t=float(k)) is None
    reason = bounds.violation(_fe(1.0, 0.05), t=10.0)  # 57 deg at once
    assert reason == "heading of r1 turned 57 deg in 10 s, more than 5 sigma of its walk (42 deg)"


def test_an_unknown_heading_is_not_judged_and_its_history_restarts() -> None:
    bounds = CalibrationBounds(TEAM, {})
    assert bounds.violation(_fe(0.0, 0.05), t=0.0) is None
    assert bounds.violation(_fe(2.0, math.pi / 2), t=5.0) is None  # spread wide: a new start
    for k in range(6, 16):
        assert bounds.violation(_fe(2.0, 0.05), t=float(k)) is None
    assert bounds.violation(_fe(2.0, 0.05), t=16.0) is None
    bounds.restart()
    assert bounds.violation(_fe(0.0, 0.05), t=17.0) is None  # no history after a restart
