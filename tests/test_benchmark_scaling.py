"""benchmarks/scaling.py: the team it builds, the floor it computes, and one tiny measured point."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from load_file import ROOT, load_module

scaling = load_module(ROOT / "benchmarks" / "scaling.py", "bench_scaling")


def test_team_has_every_pair_and_a_static_reference() -> None:
    team = scaling.make_team(6, np.random.default_rng(0))
    assert len(team.pair_a) == 15
    assert np.array_equal(team.positions(0)[0], team.positions(50)[0])
    assert np.linalg.norm(team.positions(50)[1] - team.positions(0)[1]) > 0.5


def test_floor_bytes_counts_state_ranges_and_weights() -> None:
    # 5 robots: D = 8, K = 10: 8 bytes x M x (5*8 + 2*10 + 4).
    assert scaling.floor_bytes(1000, 8, 10) == 8 * 1000 * 64


def test_a_point_reports_the_update_against_both_references(tmp_path: Path) -> None:
    out = tmp_path / "s.json"
    assert (
        scaling.main(
            [
                "--particles",
                "500",
                "--robots",
                "3",
                "--reps",
                "2",
                "--copy-mb",
                "8",
                "--hypotheses",
                "1",
                "4",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    data = json.loads(out.read_text())
    (p,) = data["particles_sweep"]
    (q,) = data["robots_sweep"]
    assert (p["robots"], p["particles"], p["dim"], p["pairs"]) == (5, 500, 8, 10)
    assert (q["robots"], q["particles"], q["dim"], q["pairs"]) == (3, 20000, 4, 3)
    for point in (p, q):
        assert point["update_s"] > point["floor_s"] > 0.0
        assert point["update_over_floor"] == point["update_s"] / point["floor_s"]
    g1, g4 = data["graph_sweep"]
    assert (g1["robots"], g1["hypotheses"], g1["dim"], g1["pairs"]) == (3, 1, 4, 3)
    assert g4["hypotheses"] == 4 and 0.0 < g1["update_s"] < 0.05
