"""The MRCLAM reference rule (``relloc.sources.mrclam.choose_reference``) on small synthetic
sessions, its command line, and the page of ``scripts/mrclam_references.py`` from fake JSON."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from load_file import ROOT, load_module

from relloc.config import TeamConfig
from relloc.sources.mrclam import (
    MrclamError,
    choose_reference,
    ground_truth_coverage,
    main,
    reference_candidates,
)

DATASET6 = ROOT.parent / "shared" / "data" / "mrclam" / "MRCLAM_Dataset6"
HEADER = "# Time [s] \t a \t b\n# synthetic\n"
BARCODES = {1: 5, 2: 14, 3: 41, 4: 32, 5: 23, 6: 90}


def _session(
    folder: Path,
    truth: dict[int, list[tuple[float, float]]],
    sightings: dict[int, list[int]] | None = None,
    start: float = 100.0,
    end: float = 200.0,
) -> Path:
    """An MRCLAM-format folder: robots ``truth``'s keys, odometry over ``[start, end]``, Vicon at
    10 Hz over each ``(from, to)`` span of ``truth[i]``, and robot ``i`` seeing the subjects
    ``sightings[i]`` (one row each) and a landmark (subject 6)."""
    folder.mkdir()
    (folder / "Barcodes.dat").write_text(
        HEADER + "".join(f"{s} \t {b}\n" for s, b in BARCODES.items())
    )
    for i, spans in truth.items():
        odo = np.linspace(start, end, 11)
        (folder / f"Robot{i}_Odometry.dat").write_text(
            HEADER + "".join(f"{t:.3f} \t 0.1 \t 0.0\n" for t in odo)
        )
        stamps = np.concatenate([np.arange(a, b + 1e-9, 0.1) for a, b in spans])
        (folder / f"Robot{i}_Groundtruth.dat").write_text(
            HEADER + "".join(f"{t:.3f} \t {i}.0 \t 0.5 \t 0.1\n" for t in stamps)
        )
        seen = [*(sightings or {}).get(i, []), 6]  # every robot sees a landmark too
        rows = "".join(
            f"{start + 1 + k:.3f} \t {BARCODES[s]} \t 2.0 \t 0.1\n" for k, s in enumerate(seen)
        )
        (folder / f"Robot{i}_Measurement.dat").write_text(HEADER + rows)
    return folder


def test_coverage_counts_the_run_only_and_leaves_dropouts_out() -> None:
    t = np.concatenate([np.arange(90.0, 150.0, 0.1), np.arange(152.0, 210.0, 0.1)])
    truth = np.column_stack([t, np.zeros((len(t), 3))])
    # [100, 200] minus the 2 s dropout, with the samples' last step before it ending at 149.9
    assert ground_truth_coverage(truth, 100.0, 200.0) == pytest.approx(97.9, abs=1e-6)
    assert ground_truth_coverage(truth, 100.0, 200.0, gap=5.0) == pytest.approx(100.0, abs=1e-6)
    assert ground_truth_coverage(truth[:1], 100.0, 200.0) == 0.0


def test_the_longest_ground_truth_wins(tmp_path: Path) -> None:
    folder = _session(
        tmp_path / "MRCLAM_Short",
        {1: [(100.0, 170.0)], 2: [(95.0, 205.0)], 3: [(100.0, 150.0), (151.0, 200.0)]},
        # robot1 is in the most sightings, but its Vicon ends 30 s early
        sightings={1: [2, 3, 2, 3], 2: [1], 3: [1]},
    )
    candidates = reference_candidates(folder)
    assert [c.robot for c in candidates] == ["robot2", "robot3", "robot1"]
    assert candidates[0].ground_truth_s == pytest.approx(100.0)
    assert candidates[1].ground_truth_s == pytest.approx(99.0, abs=0.11)  # the 1 s dropout
    assert [c.sightings for c in candidates] == [3, 3, 6]  # the landmark (subject 6) is not counted
    assert choose_reference(folder) == "robot2"


def test_ties_go_to_the_most_sightings_then_the_lowest_number(tmp_path: Path) -> None:
    whole = [(100.0, 200.0)]
    folder = _session(
        tmp_path / "MRCLAM_Tie",
        {1: whole, 2: [(100.0, 199.5)], 3: whole, 4: whole},
        sightings={1: [3], 2: [3, 3], 4: [1]},  # robot3 is seen three times: 3 sightings
    )
    assert choose_reference(folder) == "robot3"  # robot2 within the 1 s tolerance, fewer sightings
    # robot1 (saw robot3, seen by robot4) and robot2 (saw robot3 twice) tie at 2: the lower number
    assert [c.robot for c in reference_candidates(folder)] == [
        "robot3",
        "robot1",
        "robot2",
        "robot4",
    ]
    # robot1 and robot4 tie on both: the lower subject number
    assert choose_reference(folder, ("robot1", "robot4")) == "robot1"
    folder = _session(tmp_path / "MRCLAM_Plain", {4: whole, 1: whole, 2: whole})
    assert choose_reference(folder) == "robot1"


def test_the_command_line_prints_the_reference(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = _session(tmp_path / "MRCLAM_Cli", {1: [(100.0, 150.0)], 2: [(100.0, 200.0)]})
    assert main(["--reference", str(folder), "--explain"]) == 0
    out, err = capsys.readouterr()
    assert out == "robot2\n"
    assert "robot1: ground truth 50.0 s of the run" in err
    assert main(["--reference", str(tmp_path)]) == 2
    assert "not an MRCLAM data set" in capsys.readouterr().err
    with pytest.raises(MrclamError):
        reference_candidates(tmp_path)


def test_the_generic_config_holds_the_rules_answer_for_dataset_6() -> None:
    config = TeamConfig.load(ROOT / "configs" / "mrclam" / "mrclam.toml")
    dataset6 = TeamConfig.load(ROOT / "configs" / "mrclam" / "dataset6.toml")
    assert config.robot_names == dataset6.robot_names
    assert config.filter == dataset6.filter and config.area == dataset6.area
    assert [r.camera for r in config.robots] == [r.camera for r in dataset6.robots]
    if not (DATASET6 / "Barcodes.dat").is_file():
        pytest.skip(f"{DATASET6} not found (../shared/data/mrclam)")
    assert choose_reference(DATASET6) == config.reference == "robot5"
    candidates = {c.robot: c for c in reference_candidates(DATASET6)}
    assert candidates["robot1"].ground_truth_s < 800.0 < candidates["robot2"].ground_truth_s
    assert candidates["robot5"].sightings == 1913


# ------------------------------------------------------------------------- the page writer
def _script() -> ModuleType:
    return load_module(ROOT / "scripts" / "mrclam_references.py", "mrclam_references")


def _fake_run(
    folder: Path,
    reference: str,
    seed: int,
    robots: dict[str, tuple[float, float, float]],
    restarts: tuple[int, int],
    wall: float | None,
) -> None:
    """A ``relloc run --json`` file as the script leaves it: robot -> (body APE, NEES, coverage)."""
    figures = {
        name: {"ape_median": 1.0, "body_ape_median": a, "nees_median": n, "coverage95": c}
        for name, (a, n, c) in robots.items()
    }
    figures[reference] = {
        "heading_median_deg": 20.0
    }  # the reference itself has no position figures
    payload = {
        "seed": seed,
        "scenarios": {
            "MRCLAM_Fake": {
                "reference": reference,
                "methods": {"pf": {"robots": figures, "compute_s": 30.4}},
                "faults": {
                    "pf": {
                        "inconsistency_restarts": restarts[0],
                        "calibration_restarts": restarts[1],
                    }
                },
            }
        },
    }
    if wall is not None:
        payload["run"] = {"reference": reference, "seed": seed, "wall_s": wall}
    (folder / f"{reference}_s{seed}.json").write_text(json.dumps(payload))


def test_the_page_is_built_from_the_runs_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    script = _script()
    runs = tmp_path / "runs"
    runs.mkdir()
    _fake_run(
        runs,
        "robot2",
        0,
        {"robot1": (0.15, 1.8, 0.93), "robot3": (0.20, 2.5, 0.90), "robot4": (0.18, 3.0, 0.88)},
        (0, 1),
        41.3,
    )
    _fake_run(
        runs, "robot1", 1, {"robot2": (0.31, 57.6, 0.02), "robot3": (0.12, 2.0, 0.97)}, (3, 0), 95.0
    )
    _fake_run(
        runs, "robot1", 0, {"robot2": (0.21, 4.0, 0.86), "robot3": (0.10, 2.0, 0.95)}, (0, 0), None
    )
    page = tmp_path / "page.md"
    assert (
        script.main(
            [
                "--from-json",
                "--out",
                str(runs),
                "--data",
                str(tmp_path / "none"),
                "--page",
                str(page),
            ]
        )
        == 0
    )
    text = page.read_text()
    assert text in capsys.readouterr().out
    assert f"python scripts/mrclam_references.py --out {runs} --data" in text
    assert "rebuilt from that command's JSON files with `--from-json`" in text
    rows = [line for line in text.splitlines() if line.startswith("| robot")]
    assert rows[:3] == [
        "| robot1 | 0 | 0.210 (robot2) | 4.0 | 3.0 | 86 %–95 % | 0 / 0 | – | 30 |",
        "| robot1 | 1 | 0.310 (robot2) | 57.6 | 29.8 | 2 %–97 % | 3 / 0 | 95 | 30 |",
        "| robot2 | 0 | 0.200 (robot3) | 3.0 | 2.5 | 88 %–93 % | 0 / 1 | 41 | 30 |",
    ]
    assert "| robot1 | 2 | 0.310 | 57.6 | 2 % | 3 / 0 | 95 |" in text  # the per-reference table
    assert "| robot2 | 1 | 0.200 | 3.0 | 88 % | 0 / 1 | 41 |" in text
    checks = [line for line in text.splitlines() if line.startswith("- ")]
    assert checks == [
        "- FAIL: body-frame APE median <= 0.22 m for every robot: 2 of 3 runs "
        "(references passing for every seed: robot2)",
        "- FAIL: 95 % coverage within [85 %, 99 %] for every robot: 2 of 3 runs "
        "(references passing for every seed: robot2)",
        "- FAIL: NEES median <= 4 for every robot: 2 of 3 runs (references passing for every seed: robot2)",
        "- FAIL: wall time <= 90 s: 1 of 3 runs (references passing for every seed: robot2)",
    ]
    # a subset by seed, and every check passing
    assert (
        script.main(
            [
                "--from-json",
                "--out",
                str(runs),
                "--data",
                str(tmp_path),
                "--seeds",
                "0",
                "--references",
                "robot2",
                "--page",
                str(page),
            ]
        )
        == 0
    )
    text = page.read_text()
    assert [line for line in text.splitlines() if line.startswith("| robot")] == [
        "| robot2 | 0 | 0.200 (robot3) | 3.0 | 2.5 | 88 %–93 % | 0 / 1 | 41 | 30 |",
        "| robot2 | 1 | 0.200 | 3.0 | 88 % | 0 / 1 | 41 |",
    ]
    assert sum(line.startswith("- PASS") for line in text.splitlines()) == 4
    assert script.main(["--from-json", "--out", str(tmp_path / "empty")]) == 2


def test_a_missing_session_is_skipped_only_when_asked(tmp_path: Path) -> None:
    script = _script()
    assert (
        script.main(
            ["--data", str(tmp_path / "none"), "--out", str(tmp_path / "o"), "--skip-missing"]
        )
        == 0
    )
    assert script.main(["--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()
