"""The leave-one-session-out script's core on synthetic sessions (small and fast)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest
from load_file import ROOT, load_module

pytest.importorskip("torch")

from relloc.ranging.evaluate import evaluate
from relloc.ranging.synthetic import write_synthetic_csv

SCRIPT = ROOT / "scripts" / "ranging_loso.py"


def _script() -> ModuleType:
    return load_module(SCRIPT, "ranging_loso")


def test_loso_table_and_baseline(tmp_path: Path) -> None:
    loso = _script()
    sessions = {
        "a": write_synthetic_csv(tmp_path / "a.csv", robots=("1", "3", "4"), n_samples=160, seed=0),
        "b": write_synthetic_csv(
            tmp_path / "b.csv", robots=("1", "3"), n_samples=160, bias=0.35, seed=1
        ),
        "c": write_synthetic_csv(
            tmp_path / "c.csv", robots=("3", "4"), n_samples=160, bias=0.25, seed=2
        ),
    }
    configs = [loso.Candidate("stacked-base", "stacked", hidden=(4,))]
    result = loso.run_loso(sessions, tmp_path / "work", configs, epochs=2, patience=1)
    # every pair of a held-out session that another session has, and only those
    assert result.pairs == {"a": ["n_3-n_4", "n_3-n_7"], "b": ["n_3-n_7"], "c": ["n_3-n_4"]}
    assert set(result.per_pair) == {
        "zero",
        "training constant",
        "per-pair bias",
        "stacked-base",
        "stacked-base+guard",
    }
    for row in result.per_pair.values():
        assert set(row) == {"a", "b", "c"}
    # a baseline row is what the evaluation computes on the held-out session
    report = evaluate(sessions["b"], [tmp_path / "work" / "b" / "stacked-base"], part="all")
    assert result.per_pair["per-pair bias"]["b"] == report["methods"]["bias"]["per_pair_mse"]
    assert result.session_mean("zero", "b") == pytest.approx(report["methods"]["zero"]["mean_mse"])
    assert result.recommended() in result.per_pair
    page = loso.markdown(result, loso.pair_matrix(sessions), "python scripts/ranging_loso.py")
    assert "| row | a (2 pairs) | b (1 pairs) | c (1 pairs) | LOSO mean | worst pair |" in page
    assert page.count("\n| ") == 1 + 3 + 1 + len(
        result.per_pair
    )  # matrix header, pairs, table header, rows
    assert "Lowest LOSO mean" in page


def test_too_thin_for_a_choice(tmp_path: Path) -> None:
    loso = _script()
    sessions = {
        "a": write_synthetic_csv(tmp_path / "a.csv", robots=("1", "3"), n_samples=80, seed=0),
        "b": write_synthetic_csv(tmp_path / "b.csv", robots=("3", "4"), n_samples=80, seed=1),
    }
    result = loso.run_loso(sessions, tmp_path / "work", [], epochs=1, patience=1)
    assert result.pairs == {"a": [], "b": []}
    assert result.recommended() is None
    assert "No choice" in loso.markdown(result, loso.pair_matrix(sessions), "x")


def test_sessions_from_a_shared_bag(
    tmp_path: Path, shared_data: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The script's ``bag-csv`` of a shared bag: the training CSV's columns, one row per range
    with motion capture at both ends, written once and reused."""
    loso = _script()
    monkeypatch.setattr(loso, "BAGS", {"chair_20220923": loso.BAGS["chair_20220923"]})
    sessions = loso.build_sessions(shared_data, tmp_path)
    assert set(sessions) == {"train_20221219", "chair_20220923"}
    lines = sessions["chair_20220923"].read_text().splitlines()
    assert lines[0].split(",") == list(loso.CSV_COLUMNS) and len(lines) > 200
    stamp = sessions["chair_20220923"].stat().st_mtime_ns
    assert loso.build_sessions(shared_data, tmp_path)["chair_20220923"].stat().st_mtime_ns == stamp
