"""``relloc init`` on a quadrotor recording: PoseStamped motion capture on ``/<body>/world``,
LinkTrack node frames per tag on ``/n<k>/range``, two tags per drone, no odometry.

The simulated ``drones_uwb`` flight (25 s) is written as the MURP recordings lay it out; the
draft must say the team flies (``dimension = 3``), put each tag on its drone and place the tags
in 3D where the simulation put them. Ranges see only differences of the tags' heights, so z is
compared after the common height both share is taken out.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from relloc.cli import main
from relloc.config import TeamConfig
from relloc.events import pair_key
from relloc.simulator.flight import FlightSimulation, drones_six_scenario, drones_uwb_scenario
from relloc.simulator.flight_bag import tag_ids, write_flight_bag

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "uwb_drivers" / "linktrack_ros2"


def _drone_bag(
    path: Path, sim: FlightSimulation | None = None
) -> tuple[Path, dict[str, tuple[float, ...]]]:
    """A drone flight as a bag (``drones_uwb``, 25 s, by default); the true lever arm of each
    LinkTrack id (the tags numbered 1, 2, ... as the robots list them)."""
    sim = sim or drones_uwb_scenario(seed=0, duration=25.0)
    return path, write_flight_bag(path, sim, EXAMPLES)


@pytest.fixture(scope="module")
def drone_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    return _drone_bag(tmp_path_factory.mktemp("drones") / "drones")


def test_init_drafts_a_flying_team(
    drone_bag: tuple[Path, dict[str, Any]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag, truth = drone_bag
    out = tmp_path / "drones.toml"
    assert main(["init", str(bag), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    raw = tomllib.loads(out.read_text())
    assert raw["dimension"] == 3 and raw["mocap_topic"] == "/{body}/world"
    assert raw["uwb"]["range_topic"] == "/n{a}/range" and raw["uwb"]["peer_field"] == "nodes[].id"
    cfg = TeamConfig.load(out)
    assert cfg.dimension == 3
    assert {r.name: sorted(r.nodes) for r in cfg.robots} == {
        f"d{i}": sorted([str(2 * i + 1), str(2 * i + 2)]) for i in range(5)
    }
    nodes = sorted(truth)
    est = np.array([cfg.lever_arm(n) for n in nodes])
    true = np.array([truth[n] for n in nodes])
    assert est.shape == (10, 3)
    common_z = float(np.mean(true[:, 2] - est[:, 2]))  # what ranges cannot tell
    err = np.linalg.norm(est + np.array([0.0, 0.0, common_z]) - true, axis=1)
    assert err.max() < 0.05, dict(zip(nodes, err.round(3), strict=True))
    assert abs(np.mean(est[:, 2])) < 1e-3  # the tags' mean height is held at the mocap origin
    assert "dimension 3" in printed and "lever arm" in printed
    assert "range_delay" not in raw["uwb"]  # ranges at their stamps: no delay said
    # the range noise drafted is the RMS the pair biases leave, NLOS spikes included (3 % of
    # 0.3-1.5 m over 5 cm of noise, each counted at most 1 m: about 0.15 m), not their robust
    # spread (about 0.05)
    assert 0.1 < raw["uwb"]["sigma"] < 0.3 and raw["uwb"]["los_sigma"] == raw["uwb"]["sigma"]

    run = tmp_path / "run.json"
    args = ["run", str(bag), "--config", str(out), "--bias", "online", "--methods", "pf"]
    args += ["--filter-kind", "smoother3d", "--out", str(tmp_path / "run"), "--no-progress"]
    assert main([*args, "--json", str(run)]) == 0
    result = json.loads(run.read_text())["scenarios"]["drones"]["methods"]["pf"]
    assert result["n_estimates"] > 0


def test_init_no_calibrate_leaves_3d_lever_arms_to_measure(
    drone_bag: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    out = tmp_path / "bare.toml"
    assert main(["init", str(drone_bag[0]), "--out", str(out), "--no-calibrate"]) == 0
    cfg = TeamConfig.load(out)
    assert cfg.dimension == 3 and len(cfg.robots) == 5
    assert all(cfg.lever_arm(n) == (0.0, 0.0, 0.0) for r in cfg.robots for n in r.nodes)
    assert "lever arms not estimated (--no-calibrate)" in out.read_text()


def test_init_measures_the_delay_of_averaged_ranges(tmp_path: Path) -> None:
    """``drones_six``: six tags a drone, each range the mean distance over the second before
    its stamp, so it measures the geometry 0.5 s before the stamp; the draft says so
    (``uwb.range_delay``), and the lever arms fitted at the measured times hold."""
    sim = drones_six_scenario(seed=0, duration=60.0)
    ids = tag_ids(sim)
    bag, truth = _drone_bag(tmp_path / "six", sim)
    out = tmp_path / "six.toml"
    assert main(["init", str(bag), "--out", str(out)]) == 0
    raw = tomllib.loads(out.read_text())
    assert raw["dimension"] == 3
    assert 0.4 <= raw["uwb"]["range_delay"] <= 0.6, raw["uwb"]
    cfg = TeamConfig.load(out)
    assert cfg.uwb.range_delay == raw["uwb"]["range_delay"]
    nodes = sorted(truth)
    est = np.array([cfg.lever_arm(n) for n in nodes])
    true = np.array([truth[n] for n in nodes])
    common_z = float(np.mean(true[:, 2] - est[:, 2]))
    err = np.linalg.norm(est + np.array([0.0, 0.0, common_z]) - true, axis=1)
    # 1 Hz averaged ranges, 60 s: 0.03-0.07 m (fitted at the stamps, the other tags fit no body)
    assert err.max() < 0.08 and float(np.median(err)) < 0.06, dict(
        zip(nodes, err.round(3), strict=True)
    )
    # the pair biases the draft calibrates compare the ranges with the 3D tag distances at the
    # measured delay (in the plane and at the stamps: 0.15-0.72 m for biases of 0.1-0.5)
    true_bias = {
        pair_key(str(ids[a]), str(ids[b])): v
        for key, v in sim.true_biases.items()
        for a, b in [key.split("-")]
    }
    assert sorted(cfg.uwb.pairs) == sorted(true_bias)
    off = np.array([cfg.uwb.pairs[k].bias - v for k, v in true_bias.items()])
    assert np.abs(off).max() < 0.08 and off.std() < 0.03, (off.min(), off.max(), off.std())
    # and the team's range noise is what those pairs leave (3 cm simulated), not the default
    assert 0.03 <= cfg.uwb.sigma <= 0.06 and cfg.uwb.los_sigma == cfg.uwb.sigma, raw["uwb"]
    # each bias as well as this bag knows it (60 ranges a pair, 5 s blocks: about a centimetre),
    # what its online bias starts from, not the 5 cm between sessions
    errors = np.array([p.bias_sigma for p in cfg.uwb.pairs.values()])
    assert errors.min() > 0.003 and errors.max() < 0.03, (errors.min(), errors.max())
