"""``scripts/figures_check.py``: the comparison of two folders of run JSON and TUM files, on
synthetic folders (nothing is run)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import ModuleType

import pytest
from load_file import ROOT, load_module

SCRIPT = ROOT / "scripts" / "figures_check.py"


def _script() -> ModuleType:
    return load_module(SCRIPT, "figures_check")


def _run(folder: Path, name: str, ape: float, wall: float, tum: str = "0 0 0 0 0 0 0 1\n") -> None:
    """One run's JSON (with timings at two depths) and one TUM file under ``folder/name``."""
    folder.mkdir(parents=True, exist_ok=True)
    payload = {
        "seed": 0,
        "wall_s": wall,
        "scenarios": {"s": {"methods": {"pf": {"compute_s": wall / 2, "robots": {"r1": ape}}}}},
        "runs": [{"elapsed_s": wall, "ape": [ape, ape]}],
    }
    (folder / f"{name}.json").write_text(json.dumps(payload))
    (folder / name / "tum").mkdir(parents=True, exist_ok=True)
    (folder / name / "tum" / "r1.txt").write_text(tum)


@pytest.fixture
def before(tmp_path: Path) -> Path:
    a = tmp_path / "before"
    _run(a, "demo", 0.1, 3.0)
    _run(a, "shortbag", 0.2, 9.0)
    return a


def _copy(before: Path) -> Path:
    after = before.parent / "after"
    shutil.copytree(before, after)
    return after


def test_identical_folders(before: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _script().compare(before, _copy(before)) == 0
    assert capsys.readouterr().out.splitlines() == [
        "demo: identical (1 TUM files)",
        "shortbag: identical (1 TUM files)",
    ]


def test_timings_alone_are_ignored(before: Path, capsys: pytest.CaptureFixture[str]) -> None:
    after = _copy(before)
    _run(after, "demo", 0.1, 4.5)
    assert _script().compare(before, after) == 0
    assert "demo: identical (1 TUM files)" in capsys.readouterr().out


def test_a_changed_figure_is_a_difference(before: Path, capsys: pytest.CaptureFixture[str]) -> None:
    after = _copy(before)
    _run(after, "shortbag", 0.2000001, 9.0)
    assert _script().compare(before, after) == 1
    assert capsys.readouterr().out.splitlines()[1] == "shortbag: DIFFERENT (1 TUM files)"


def test_a_changed_trajectory_file_is_a_difference(
    before: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    after = _copy(before)
    (after / "demo" / "tum" / "r1.txt").write_text("0 0 0 0 0 0 0 1.0\n")
    assert _script().compare(before, after) == 1
    assert capsys.readouterr().out.splitlines()[0] == "demo: DIFFERENT (TUM files differ: r1.txt)"


def test_a_missing_run_or_trajectory_file(before: Path, capsys: pytest.CaptureFixture[str]) -> None:
    after = _copy(before)
    (after / "shortbag.json").unlink()
    (after / "demo" / "tum" / "r1.txt").unlink()
    assert _script().compare(before, after) == 2
    assert capsys.readouterr().out.splitlines() == [
        "demo: DIFFERENT (TUM files differ: r1.txt)",
        f"shortbag: missing in {after}",
    ]
