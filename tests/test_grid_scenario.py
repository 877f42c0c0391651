"""Tests of the scaling scenario ``grid``: N robots on a grid, all pairs ranging, a static reference."""

from __future__ import annotations

import json
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest

from relloc.cli import main
from relloc.events import GroundTruthEvent, RangeEvent
from relloc.runs.demo import SCENARIOS, DemoOptions, build_simulation, scenario_setup
from relloc.simulator.scenarios import grid_scenario


@pytest.mark.parametrize("n", [3, 10])
def test_every_pair_ranges_and_the_reference_is_static(n: int) -> None:
    sim = grid_scenario(0, robots=n, duration=4.0)
    events = list(sim.events())
    ranges = [e for e in events if isinstance(e, RangeEvent)]
    pairs = {frozenset((e.robot_a, e.robot_b)) for e in ranges}
    robots = [f"r{i}" for i in range(n)]
    assert sim.robots == tuple(robots) and sim.reference == "r0"
    assert pairs == {frozenset(p) for p in combinations(robots, 2)}
    assert len(sim.true_biases) == n * (n - 1) // 2
    # 10 Hz per pair over 4 s, less dropouts: every pair has most of its 40 ranges.
    per_pair = [sum(frozenset((e.robot_a, e.robot_b)) == p for e in ranges) for p in pairs]
    assert min(per_pair) >= 30
    t = np.arange(0.0, sim.duration, 0.05)
    assert np.ptp(sim.true_poses("r0", t)[:, :2], axis=0).max() == 0.0
    xmin, xmax, ymin, ymax = sim.config.area
    gt = [e for e in events if isinstance(e, GroundTruthEvent)]
    assert all(xmin < e.position[0] < xmax and ymin < e.position[1] < ymax for e in gt)
    for r in robots[1:]:
        p = sim.true_poses(r, t)[:, :2]
        path = np.hypot(*np.diff(p, axis=0).T).sum()
        assert 0.2 * sim.duration * 0.95 < path < 0.3 * sim.duration * 1.05  # 0.2-0.3 m/s circles
    # Neighbouring cells are 3 m apart: no two robots' circles overlap.
    pos = np.stack([sim.true_poses(r, t)[:, :2] for r in robots])
    gaps = [np.linalg.norm(pos[a] - pos[b], axis=1).min() for a, b in combinations(range(n), 2)]
    assert min(gaps) > 0.7


def test_deterministic_for_a_seed_and_different_across_seeds() -> None:
    a = list(grid_scenario(2, robots=4, duration=3.0).events())
    b = list(grid_scenario(2, robots=4, duration=3.0).events())
    c = list(grid_scenario(3, robots=4, duration=3.0).events())
    assert a == b
    assert a != c


def test_adding_a_robot_keeps_the_noise_of_existing_pairs() -> None:
    """Each pair's errors are on their own streams: a larger team leaves r0-r1's ranges alone
    (the grid's layout moves the cells, so compare the range errors, not the ranges)."""

    def errors(n: int) -> np.ndarray:
        sim = grid_scenario(1, robots=n, duration=3.0)
        ev = [
            e
            for e in sim.events()
            if isinstance(e, RangeEvent) and {e.robot_a, e.robot_b} == {"r0", "r1"}
        ]
        t = np.array([e.t for e in ev])
        true = np.linalg.norm(
            sim.true_poses("r0", t)[:, :2] - sim.true_poses("r1", t)[:, :2], axis=1
        )
        return np.array([e.distance for e in ev]) - true

    e4, e9 = errors(4), errors(9)
    assert e4.shape == e9.shape
    assert np.std(e4 - e9) < 0.05  # the same noise draws; only the geometry-dependent part differs


def test_demo_registers_grid_outside_the_default_set() -> None:
    assert SCENARIOS["grid"] is grid_scenario
    assert "grid" not in DemoOptions().scenarios
    sim = build_simulation("grid", DemoOptions(robots=7))
    assert len(sim.robots) == 7 and sim.duration == 40.0
    # Heading-estimate mode: a moving robot is the reference (the static r0 would leave the
    # formation's bearing unobservable).
    _, config, _ = scenario_setup("grid", DemoOptions(robots=3, heading="estimate"))
    assert config.reference == "r1"


def test_too_small_a_team_is_refused() -> None:
    with pytest.raises(ValueError, match="at least 2"):
        grid_scenario(0, robots=1)


def test_demo_runs_the_grid_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "grid.json"
    rc = main(
        [
            "demo",
            "--scenarios",
            "grid",
            "--robots",
            "3",
            "--particles",
            "2000",
            "--seed",
            "0",
            "--json",
            str(path),
            "--out",
            str(tmp_path / "o"),
            "--no-progress",
        ]
    )
    assert rc == 0
    methods = json.loads(path.read_text())["scenarios"]["grid"]["methods"]
    assert set(methods["pf"]["robots"]) == {"r1", "r2"}
    assert all(r["n"] > 250 for r in methods["pf"]["robots"].values())
    assert methods["pf"]["mean_ape_median"] < 0.5
    assert main(["demo", "--scenarios", "grid", "--robots", "1", "--no-progress"]) == 2
    assert "at least 2 robots" in capsys.readouterr().err
