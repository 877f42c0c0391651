"""``scripts/transport_ab.py``: its arguments, medians and Markdown block, on made-up runs (no
process is started)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "transport_ab.py"


@pytest.fixture(scope="module")
def ab() -> ModuleType:
    spec = importlib.util.spec_from_file_location("transport_ab", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_arguments(ab: ModuleType, tmp_path: Path) -> None:
    args = ab.parse_args([])
    assert (args.runs, args.seed, args.ape, args.json, args.markdown) == (10, 0, False, None, None)
    args = ab.parse_args(["--runs", "1", "--seed", "3", "--out", str(tmp_path), "--ape"])
    assert (args.runs, args.seed, args.out, args.ape) == (1, 3, tmp_path, True)
    with pytest.raises(SystemExit):
        ab.parse_args(["--runs", "0"])


def fake_result(ab: ModuleType) -> dict:
    runs = [
        {"transport": "tls", "tracking_median": 0.07, "ape_median": 0.13},
        {"transport": "plain", "tracking_median": 0.06, "ape_median": None},
        {"transport": "tls", "tracking_median": 0.09, "ape_median": 0.15},
        {"transport": "plain", "tracking_median": 0.08, "ape_median": None},
        {"transport": "tls", "tracking_median": None, "ape_median": None, "error": "timed out"},
        {"transport": "plain", "tracking_median": 0.10, "ape_median": None},
    ]
    return {
        "command": "scripts/transport_ab.py --runs 3",
        "runs": runs,
        "medians": ab.summarise(runs),
    }


def test_medians_leave_out_failed_runs(ab: ModuleType) -> None:
    m = fake_result(ab)["medians"]
    assert m["tls"]["tracking_median"] == {
        "median": pytest.approx(0.08),
        "min": 0.07,
        "max": 0.09,
        "n": 2,
    }
    assert m["plain"]["tracking_median"]["median"] == pytest.approx(0.08)
    assert m["plain"]["ape_median"] == {"median": None, "min": None, "max": None, "n": 0}
    assert m["tls_minus_plain"]["tracking_median"] == pytest.approx(0.0)
    assert m["tls_minus_plain"]["ape_median"] is None


def test_markdown_block_is_replaced_between_the_markers(ab: ModuleType, tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text(f"# Title\n\nbefore\n\n{ab.BEGIN}\nold table\n{ab.END}\n\nafter\n")
    text = ab.table(fake_result(ab))
    ab.write_markdown(page, text)
    ab.write_markdown(page, text)  # idempotent
    out = page.read_text()
    assert out == f"# Title\n\nbefore\n\n{ab.BEGIN}\n{text}\n{ab.END}\n\nafter\n"
    assert "| mutual TLS | 0.080 m (0.070-0.090), n=2 | 0.140 m (0.130-0.150), n=2 |" in out
    assert "| plain TCP | 0.080 m (0.060-0.100), n=3 | - |" in out
    assert "| TLS - plain | +0.000 m | - |" in out


def test_markdown_block_is_appended_where_there_is_none(ab: ModuleType, tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("text")
    ab.write_markdown(page, "table")
    assert page.read_text() == f"text\n{ab.BEGIN}\ntable\n{ab.END}\n"
    ab.write_markdown(tmp_path / "new.md", "table")
    assert (tmp_path / "new.md").read_text() == f"{ab.BEGIN}\ntable\n{ab.END}\n"
    (tmp_path / "half.md").write_text(f"{ab.BEGIN}\n")
    with pytest.raises(ValueError, match="one transport_ab marker"):
        ab.write_markdown(tmp_path / "half.md", "table")
