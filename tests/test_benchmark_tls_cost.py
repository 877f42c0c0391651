"""benchmarks/tls_cost.py without processes: the live rectangles' table, as ``--readme``
writes it between its markers."""

from __future__ import annotations

from pathlib import Path

from load_file import ROOT, load_module

from relloc.evaluation.pages import markers

bench = load_module(ROOT / "benchmarks" / "tls_cost.py", "bench_tls_cost")


def test_the_rectangles_table_gives_medians_ranges_and_the_difference(tmp_path: Path) -> None:
    def run(tracking: float, ape: float) -> dict[str, float]:
        return {"tracking_median_m": tracking, "ape_median_m": ape}

    rect = {
        "runs": {
            "plain": [run(0.070, 0.130), run(0.080, 0.150), run(0.075, 0.140)],
            "tls": [run(0.072, 0.131), run(0.090, 0.160), run(0.071, 0.135)],
        },
        "median": {"plain": run(0.075, 0.140), "tls": run(0.072, 0.135)},
    }
    table = bench.rectangle_table(rect, 0.1)
    assert "`--reorder-window 0.1`; runs alternated, 3 per transport" in table
    assert "| plain TCP | 0.075 m (0.070-0.080) | 0.140 m (0.130-0.150) |" in table
    assert "| mutual TLS | 0.072 m (0.071-0.090) | 0.135 m (0.131-0.160) |" in table
    assert "| TLS - plain | -0.003 m | -0.005 m |" in table
    page = tmp_path / "secure.md"
    begin, end = markers("tls_rectangle")
    page.write_text(f"before\n{begin}\nold\n{end}\nafter\n")
    bench.write_between(page, "tls_rectangle", table)
    text = page.read_text()
    assert text.startswith("before\n") and text.endswith(f"{end}\nafter\n") and "old" not in text
