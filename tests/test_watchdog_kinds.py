"""The consistency watchdog in every filter kind: a robot displaced 1 m, or slipping 0.4 m/s,
unseen by its odometry is flagged within 10 s of stream time; clean runs raise no flag."""

from __future__ import annotations

import pytest

from relloc.engine import Engine
from relloc.faults import Faults, inject
from relloc.localizers.watchdog import ConsistencyWatchdog
from relloc.methods import build_pipeline
from relloc.simulator import multi_scenario

KINDS = ("particle", "gaussian_sum", "range_graph", "smoother")
SMALL = {"particles": 2000, "selfcal_particles": 200, "selfcal_init_particles": 2000}
ONSET = 15.0
"""When the fault begins (the filters have converged by then)."""
BOUND = 10.0
"""Stream seconds from the onset within which the watchdog must flag."""
CLEAN = Faults()


def _drift(robot: str, speed: float, start: float, end: float) -> Faults:
    """``robot`` slips ``speed`` m/s along x from ``start``, unseen by its odometry: kidnappings
    of ``speed / 10`` m every 0.1 s (ground truth and ranges follow)."""
    steps = round((end - start) * 10)
    return Faults(kidnap=tuple((robot, start + 0.1 * k, 0.1 * speed, 0.0) for k in range(steps)))


def _flags(
    kind: str, seed: int, duration: float, faults: Faults = CLEAN
) -> tuple[list[float], int]:
    """The stamps of the estimates marked inconsistent, and the watchdog's episodes."""
    sim = multi_scenario(seed=seed, duration=duration)
    pipeline = build_pipeline("pf", sim.config.with_filter(kind=kind, **SMALL), seed=seed)
    Engine([pipeline]).run(inject(sim.events(), faults))
    watchdog = pipeline.localizer.watchdog
    assert isinstance(watchdog, ConsistencyWatchdog)
    return [e.t for e in pipeline.estimates if e.inconsistent], watchdog.episodes


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(
    "fault",
    [
        pytest.param(Faults(kidnap=(("r2", ONSET, 1.0, 0.0),)), id="step-1m"),
        pytest.param(_drift("r2", 0.4, ONSET, ONSET + BOUND + 1.0), id="drift-0.4"),
    ],
)
def test_a_step_or_a_drift_is_flagged_within_10_s(kind: str, fault: Faults) -> None:
    flags, episodes = _flags(kind, 0, ONSET + BOUND + 1.0, fault)
    assert flags and episodes >= 1
    assert ONSET <= flags[0] <= ONSET + BOUND, f"first flag at {flags[0]:.2f} s, onset {ONSET} s"


@pytest.mark.parametrize("kind", KINDS)
def test_clean_runs_raise_no_flag(kind: str) -> None:
    """Seeds 0-9, 15 s each (the filters converge within the first seconds)."""
    flagged = {}
    for seed in range(10):
        flags, episodes = _flags(kind, seed, 15.0)
        if flags or episodes:
            flagged[seed] = (flags[:3], episodes)
    assert flagged == {}
