"""The consistency watchdog (innovations against the published covariance, per robot) and the
calibration bounds."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace
from typing import cast

import numpy as np
import pytest

from relloc.config import RobotConfig, TeamConfig
from relloc.estimate import Estimate
from relloc.estimators.gaussian_sum.localizer import SelfCalibratingLocalizer
from relloc.events import GroundTruthEvent, RangeEvent, SightingEvent
from relloc.filter.base import FilterEstimate
from relloc.filter.calibration import CalibrationNoise
from relloc.filter.state import StateLayout
from relloc.filter.summary import ModeSummary
from relloc.localizers.bounds import CalibrationBounds
from relloc.localizers.watchdog import WINDOW, ConsistencyWatchdog
from relloc.navigation.safety import SafetyGate
from relloc.simulator import multi_scenario

TEAM = TeamConfig((RobotConfig("r0"), RobotConfig("r1"), RobotConfig("r2")), "r0")
TRUTH = {"r0": (0.0, 0.0), "r1": (3.0, 0.0), "r2": (0.0, 4.0)}


def _ranges(
    t: float, where: dict[str, tuple[float, float]], rng: np.random.Generator
) -> list[RangeEvent]:
    """The three pairs' ranges of the formation ``where``, with the config's noise."""
    sigma = TEAM.uwb.sigma
    out = []
    for a, b in (("r0", "r1"), ("r0", "r2"), ("r1", "r2")):
        d = math.dist(where[a], where[b]) + float(rng.normal(0.0, sigma))
        out.append(RangeEvent(t, a, b, d, corrected=True))
    return out


def _estimate(where: dict[str, tuple[float, float]], std: float) -> FilterEstimate:
    mean = np.array([where["r1"], where["r2"]])
    return FilterEstimate(mean, np.tile(np.eye(2) * std**2, (2, 1, 1)), 100.0)


def _feed(
    dog: ConsistencyWatchdog, seconds: tuple[float, float], ranges_from: dict, fe: FilterEstimate
) -> list[float]:
    """Ten batches a second of ranges from ``ranges_from``; the times the dog asked for a restart."""
    rng = np.random.default_rng(0)
    restarts = []
    for t in np.arange(*seconds, 0.1):
        if dog.observe(float(t), _ranges(float(t), ranges_from, rng), fe):
            restarts.append(float(t))
    return restarts


def test_a_consistent_estimate_is_never_flagged() -> None:
    dog = ConsistencyWatchdog(TEAM, StateLayout(TEAM.robot_names, "r0"))
    assert _feed(dog, (0.0, 60.0), TRUTH, _estimate(TRUTH, 0.1)) == []
    assert not dog.inconsistent and dog.widening == 1.0 and dog.episodes == 0


def test_ranges_from_another_formation_are_flagged_within_10_s_and_cleared() -> None:
    """r2 ranged at (1, 3.4), 1.2 m from where a confident estimate (0.05 m) holds it: flagged
    within a window, widened by what the innovations say, retried after a fresh window without
    help, cleared once the estimate fits again."""
    dog = ConsistencyWatchdog(TEAM, StateLayout(TEAM.robot_names, "r0"))
    moved = {**TRUTH, "r2": (1.0, 3.4)}
    fe = _estimate(TRUTH, 0.05)
    assert _feed(dog, (0.0, 20.0), TRUTH, fe) == []
    restarts = _feed(dog, (20.0, 40.0), moved, fe)
    assert restarts and 20.0 < restarts[0] <= 20.0 + WINDOW
    assert dog.inconsistent and dog.episodes == 1
    assert dog.widening > 10.0  # the median NIS over the chi-square median
    dog.restart(restarts[0])
    assert dog.widening == 1.0  # no fresh innovation yet
    assert _feed(dog, (40.0, 60.0), moved, _estimate(moved, 0.05)) == []
    assert not dog.inconsistent and dog.widening == 1.0 and dog.episodes == 1


def test_a_sightings_range_and_bearing_count_where_the_frame_is_known() -> None:
    """r1 at (3, 0) sees r2 at (0, 4): 5 m away, at 126.87 deg in the published frame."""
    fe = _estimate(TRUTH, 0.05)
    direction = math.atan2(4.0, -3.0)
    dog = ConsistencyWatchdog(TEAM, StateLayout(TEAM.robot_names, "r0"))
    right = [SightingEvent(0.1 * k, "r1", "r2", 5.0, direction - 0.5, 0.1, 0.01) for k in range(12)]
    assert not dog.observe(1.2, right, fe, {"r1": 0.5}) and not dog.inconsistent
    # the bearing 0.2 rad off: flagged with the frame known, not judged without one
    turned = [
        SightingEvent(10.0 + 0.1 * k, "r1", "r2", None, direction - 0.3, 0.1, 0.01)
        for k in range(12)
    ]
    assert not ConsistencyWatchdog(TEAM, StateLayout(TEAM.robot_names, "r0")).observe(
        11.2, turned, fe
    )
    assert dog.observe(11.2, turned, fe, {"r1": 0.5}) and dog.inconsistent
    # a published heading of r1 turns its yaw and its spread widens the bound
    dog = ConsistencyWatchdog(TEAM, StateLayout(TEAM.robot_names, "r0"))
    headed = FilterEstimate(fe.mean, fe.cov, fe.ess, headings={"r1": (-0.2, 0.3)})
    assert not dog.observe(11.2, turned, headed, {"r1": 0.5 + 0.2})
    far = [SightingEvent(20.0 + 0.1 * k, "r1", "r2", 7.0, None, 0.1) for k in range(12)]
    assert dog.observe(21.2, far, headed, {"r1": 0.7})
    assert dog.widening > 1.0


def _raw_ranges(t: float, offset: float, rng: np.random.Generator) -> list[RangeEvent]:
    """The three pairs' raw ranges (uncalibrated: the default bias assumed) of ``TRUTH``, each
    ``offset`` longer than that bias says, with line-of-sight noise."""
    uwb = TEAM.uwb
    return [
        RangeEvent(
            t,
            a,
            b,
            math.dist(TRUTH[a], TRUTH[b])
            + uwb.default_bias
            + offset
            + float(rng.normal(0.0, uwb.los_sigma)),
        )
        for a, b in (("r0", "r1"), ("r0", "r2"), ("r1", "r2"))
    ]


@pytest.mark.parametrize(("offset", "flagged"), [(0.25, False), (-0.2, False), (1.0, True)])
def test_a_range_is_judged_by_the_error_the_filter_assumes(offset: float, flagged: bool) -> None:
    """An uncalibrated pair's bias off by 0.25 m is within what the filter's likelihood assumes
    (``default_bias_sigma`` 0.15 m over ``los_sigma`` 0.1 m, the NLOS part): not flagged
    against a confident estimate; 1 m off is."""
    dog = ConsistencyWatchdog(TEAM, StateLayout(TEAM.robot_names, "r0"))
    fe = _estimate(TRUTH, 0.02)
    rng = np.random.default_rng(0)
    restarts = [
        t
        for t in np.arange(0.0, 60.0, 0.1)
        if dog.observe(float(t), _raw_ranges(float(t), offset, rng), fe)
    ]
    assert bool(restarts) is flagged and dog.episodes == int(flagged)


def test_a_range_is_judged_against_the_pairs_distance_over_the_dominant_mode() -> None:
    """A cloud spread over every direction (its mean positions at the origin, their covariances
    wide) whose mode knows the distances: judged on them (0.05 m spread), not on the mean
    positions' distance; ranges 1 m longer than the mode's distances are flagged."""
    mean = np.array([[0.0, 0.01], [0.01, 0.0]])
    distances = np.zeros((3, 3, 2))
    for i, a in enumerate(("r0", "r1", "r2")):
        for j, b in enumerate(("r0", "r1", "r2")):
            distances[i, j] = (math.dist(TRUTH[a], TRUTH[b]), 0.05 if i != j else 0.0)
    summary = cast(ModeSummary, SimpleNamespace(distances=distances))
    fe = FilterEstimate(mean, np.tile(np.eye(2) * 9.0, (2, 1, 1)), 100.0, summary=summary)
    dog = ConsistencyWatchdog(TEAM, StateLayout(TEAM.robot_names, "r0"))
    assert _feed(dog, (0.0, 30.0), TRUTH, fe) == []
    shorter = distances.copy()
    shorter[..., 0] -= 1.0
    far = FilterEstimate(
        mean, fe.cov, 100.0, summary=cast(ModeSummary, SimpleNamespace(distances=shorter))
    )
    assert _feed(dog, (30.0, 40.0), TRUTH, far)


def test_the_estimate_says_it_and_the_navigation_gate_holds() -> None:
    est = Estimate(
        1.0, "pf", "r0", {"r1": (3.0, 0.0)}, {"r1": ((0.01, 0.0), (0.0, 0.01))}, inconsistent=True
    )
    assert est.status.startswith("inconsistent: ")
    assert SafetyGate(robot="r1").check(1.0, est, 1.0) == (
        "inconsistent",
        "the estimate's covariance no longer covers its innovations",
    )


# ---------------------------------------------------------------------------- calibration bounds
def test_a_scale_driven_out_of_its_interval_is_restarted() -> None:
    """r2's odometry scale pushed to 0.3 in every Gaussian (a runaway): the next step says why,
    restarts the calibration from its prior (1 +- scale_prior_sigma) and counts it."""
    sim = multi_scenario(seed=0, duration=14.0)
    loc = SelfCalibratingLocalizer(sim.config.with_modes(odom_scale="online"), seed=0)
    events = [ev for ev in sim.events() if not isinstance(ev, GroundTruthEvent)]
    ests = [est for ev in events[: len(events) // 2] for est in loc.process(ev)]
    assert ests and loc.fault_counters()["calibration_restarts"] == 0
    assert 0.5 < ests[-1].scales["r2"][0] < 1.5
    gsf = loc.filter
    # the bounds stand behind the filter's own truncation of each Gaussian's scale
    # (GaussianSumFilter.constrain_scales), switched off here to reach them
    gsf.noise = dataclasses.replace(gsf.noise, scale_bounds=(0.0, math.inf))
    gsf.mean[:, gsf.layout.scale_column("r2")] = 0.3
    ests = [est for ev in events[len(events) // 2 :] for est in loc.process(ev)]
    counters = loc.fault_counters()
    assert counters["calibration_restarts"] == 1
    assert (
        counters["calibration_restart_reason"] == "odometry scale of r2 at 0.299, outside 0.5..1.5"
    )  # after one update
    assert all(0.5 < s < 1.5 for e in ests for s, _ in e.scales.values())
    prior = CalibrationNoise().scale_prior_sigma
    assert ests[0].scales["r2"][1] == pytest.approx(prior, rel=0.2)  # its prior again


def test_a_bias_far_from_its_prior_is_out_of_bounds() -> None:
    bounds = CalibrationBounds(TEAM, {"n0|n1": (0.1, 0.05)})
    fe = _estimate(TRUTH, 0.1)
    assert bounds.violation(dataclasses.replace(fe, biases={"n0|n1": (0.3, 0.01)})) is None
    assert bounds.violation(dataclasses.replace(fe, biases={"n0|n1": (0.4, 0.01)})) == (
        "range bias of n0|n1 at 0.400 m, more than 5 sigma from its prior"
    )
    assert bounds.violation(dataclasses.replace(fe, scales={"r1": (1.6, 0.01)})) == (
        "odometry scale of r1 at 1.600, outside 0.5..1.5"
    )
