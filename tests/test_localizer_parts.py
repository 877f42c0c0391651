"""The localizer's collaborators on their own: the team clock, the batching grid and its wake
rule, the hooks that the measurement models and the filters give the localizer."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pytest

from relloc.config import TeamConfig
from relloc.estimators.particle.filter import ParticleFilter
from relloc.estimators.range_graph.filter import RangeGraphFilter
from relloc.events import WAKE_ALWAYS, OdometryEvent, RangeEvent, RelativeObservation, SightingEvent
from relloc.filter.measurement import MeasurementModel, hook
from relloc.filter.ranges import RangeBatch
from relloc.filter.registry import model_for
from relloc.filter.sightings import SightingBatch
from relloc.filter.state import StateLayout
from relloc.filter.vectors import RelativePositionBatch
from relloc.localizers.clock import TeamClock, stream
from relloc.localizers.grid import BatchGrid


def _odometry(t: float, robot: str = "r1") -> OdometryEvent:
    return OdometryEvent(t, robot, 0.0, 0.0, 0.0, 0.0, 0.0)


# ---------------------------------------------------------------------------- model hooks
def test_the_models_say_which_stream_an_event_is_and_whom_it_is_news_of() -> None:
    r = RangeEvent(1.0, "r2", "r1", 3.0)
    s = SightingEvent(1.0, "r1", "r3", 2.0, 0.5)
    v = RelativeObservation(1.0, "r3", "r2", (1.0, 0.0), 0.1)
    assert RangeBatch.stream(r) == stream(r) == ("range", "r1", "r2")
    assert stream(s) == ("SightingEvent", "r1") and stream(v) == ("RelativeObservation", "r3")
    assert stream(_odometry(1.0, "r2")) == ("OdometryEvent", "r2")
    assert (RangeBatch.heard(r), SightingBatch.heard(s), RelativePositionBatch.heard(v)) == (
        ("r2", "r1"), ("r1", "r3"), ("r3", "r2"),
    )  # fmt: skip
    assert [hook(model_for(e), "ranged") for e in (r, s, v)] == [True, False, False]  # type: ignore[arg-type]


def test_a_model_without_the_hooks_gets_the_protocol_defaults() -> None:
    class Bare:  # follows the protocol without subclassing it, and without the optional hooks
        pass

    event = _odometry(2.0, "r4")
    assert hook(Bare, "stream")(event) == ("OdometryEvent", "r4") == MeasurementModel.stream(event)  # type: ignore[arg-type]
    assert hook(Bare, "heard")(event) == () and hook(Bare, "ranged") is False  # type: ignore[arg-type]
    assert hook(RangeBatch, "ranged") is True


# ---------------------------------------------------------------------------- the clock
def test_the_clock_is_set_by_the_median_of_the_first_events_of_two_streams() -> None:
    clock = TeamClock(max_time_jump=10.0)
    first = [_odometry(t) for t in (5.0, 1.0, 2.0, 900.0)]
    assert all(clock.warm(e) == [] for e in first) and not clock.started
    assert clock.warm(_odometry(4.0)) == []  # five events of one stream: not yet
    ranged = RangeEvent(3.0, "r1", "r2", 2.0)
    assert clock.warm(ranged) == [*first, _odometry(4.0), ranged]
    assert clock.started and clock.now == 3.5
    assert clock.check(first[3], lambda e: False) == "time_jump"  # the outlier among them


def test_three_votes_of_two_streams_follow_a_jump_and_accepted_events_wear_them_down() -> None:
    clock = TeamClock(max_time_jump=10.0)
    clock.now = 100.0
    clock.accepted(_odometry(100.0))
    clock.accepted(RangeEvent(100.0, "r1", "r2", 2.0))
    late = lambda e: True  # noqa: E731
    assert clock.check(_odometry(500.0, "r1"), late) == "time_jump"
    assert clock.check(_odometry(500.1, "r1"), late) == "time_jump"
    clock.accepted(_odometry(100.1))  # one vote less
    assert clock.check(_odometry(500.2, "r1"), late) == "time_jump"  # two votes, one stream
    assert clock.check(RangeEvent(500.3, "r1", "r2", 2.0), late) == "follow"
    clock.follow(400.3)
    assert clock.now == pytest.approx(500.3)
    assert clock.check(_odometry(80.0), lambda e: False) is None  # behind, but still usable
    assert clock.check(_odometry(80.0), late) == "time_jump_backward"


# ---------------------------------------------------------------------------- the grid
def test_the_wake_rule_is_the_grid_s_own_bounds() -> None:
    """The rule wakes for exactly the events that close the pending batch, up to its margin:
    a measurement of the next cell, odometry two cells on."""
    grid = BatchGrid(update_period=0.1)
    assert grid.wake_rule(-math.inf, 1.0) == WAKE_ALWAYS
    assert grid.wake_rule(20.0, 1.0) == (-math.inf, math.inf, 19.00001, 20.99999)
    grid.add(RangeEvent(20.03, "r1", "r2", 2.0))
    rule = grid.wake_rule(20.03, 1.0)
    assert rule.measurement_from == pytest.approx(
        20.1 - 1e-5
    ) and rule.odometry_from == pytest.approx(20.2 - 1e-5)
    for t in (20.05, 20.0999, 20.1001, 20.15, 20.1999, 20.2001, 20.3):
        assert grid.closed_by(t) == (t >= 20.1), t
        assert grid.due(t) == (t >= 20.2), t
        assert rule.urgent(t, odometry=False) == grid.closed_by(t)
        assert rule.urgent(t, odometry=True) == grid.due(t)
    t, batch = grid.take()
    assert (
        (t, len(batch), grid.pending) == (20.03, 1, [])
        and grid.is_late(20.02)
        and not grid.is_late(20.03)
    )


# ---------------------------------------------------------------------------- filter hooks
def test_only_the_particle_filter_restarts_and_pauses_its_kernel() -> None:
    layout = StateLayout(("r0", "r1", "r2"), "r0")
    pf = ParticleFilter(layout, 100, (-4, 4, -4, 4), rng=np.random.default_rng(0))
    pf.pause_kernel(True)
    assert pf.kernel_paused and pf.posterior_wide
    pf.pause_kernel(False)
    assert not pf.kernel_paused
    graph = RangeGraphFilter(layout, (-4, 4, -4, 4), rng=np.random.default_rng(0))
    graph.pause_kernel(True)  # nothing to pause
    assert graph.restart([RangeEvent(1.0, "r0", "r1", 2.0)], None, None) is False  # type: ignore[arg-type]


# ---------------------------------------------------------------------------- step timer
def test_the_step_timer_is_called_once_per_step_with_its_duration() -> None:
    from relloc.estimate import Estimate
    from relloc.events import GroundTruthEvent
    from relloc.localizers.base import Localizer
    from relloc.runs.demo import DemoOptions, scenario_setup

    class Counted(Localizer):
        def __init__(self, config: TeamConfig) -> None:
            super().__init__(config)
            self.steps: list[float] = []

        def _step(self, t: float, batch: list[Any]) -> Estimate | None:
            self.steps.append(t)
            time.sleep(1e-4)
            return None

    sim, config, _ = scenario_setup("single", DemoOptions(seed=0))
    loc = Counted(config)
    calls: list[tuple[float, float, Estimate | None]] = []
    loc.step_timer = lambda t, seconds, est: calls.append((t, seconds, est))
    events = [e for e in sim.events() if not isinstance(e, GroundTruthEvent)]
    for event in events[:2000]:
        loc.process(event)
    loc.flush()
    assert loc.steps and [t for t, _, _ in calls] == loc.steps
    assert all(seconds >= 1e-4 and est is None for _, seconds, est in calls)
