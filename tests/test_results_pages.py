"""``scripts/results_pages.py``: the generated results page and the first-run tutorial's output.

The renderers are checked on small JSON documents shaped like the benchmarks' ``--json``; one
``--quick`` run checks the whole script end to end (the demo's ``single`` scenario and two
tiny benchmarks, a few seconds).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from load_file import ROOT, load_module

SCRIPT = ROOT / "scripts" / "results_pages.py"


@pytest.fixture(scope="module")
def pages():
    return load_module(SCRIPT, "results_pages")


def test_every_benchmark_has_a_renderer_and_a_script(pages) -> None:
    for quick in (False, True):
        for name in pages.benchmarks(quick):
            assert name in pages.BENCH_PAGES
            assert (ROOT / "benchmarks" / f"{name}.py").exists()


def test_benchmark_section_reads_the_json(pages, tmp_path: Path) -> None:
    path = tmp_path / "cdr_codecs.json"
    path.write_text(
        json.dumps({"decode Range": {"relloc_us": 1.5, "rosbags_us": 6.0, "speedup": 4.0}})
    )
    text = "\n".join(pages.bench_section("cdr_codecs", ["--n", "10"], path, "ok"))
    assert "python benchmarks/cdr_codecs.py --n 10 --json cdr_codecs.json" in text
    assert "| decode Range | 1.50 µs | 6.00 µs | 4.0x |" in text


def test_a_missing_json_says_why(pages, tmp_path: Path) -> None:
    text = "\n".join(
        pages.bench_section(
            "filter_vs_pfilter", [], tmp_path / "none.json", "pfilter is not installed here."
        )
    )
    assert "Not run: pfilter is not installed here." in text
    text = "\n".join(pages.run_section("mrclam6", ["run", "x"], tmp_path / "none.json", "no data"))
    assert "Not run: no data" in text


def test_pfilter_and_tls_tables(pages) -> None:
    pf = pages.pfilter_table({"400": {"relloc_s": 2.5e-4, "pfilter_s": 1.5e-3, "speedup": 6.0}})
    assert pf[-1] == "| 400 | 0.25 ms | 1.50 ms | 6.0x |"
    row = {
        "paced_cpu_us_per_msg": 100.0,
        "latency_median_us": 50.0,
        "latency_p99_us": 200.0,
        "burst_cpu_us_per_msg": 3.0,
        "burst_msgs_per_s": 2e5,
    }
    tls = pages.tls_table(
        {"transport": {"median": {"plain": row, "tls": {**row, "latency_median_us": 100.0}}}}
    )
    assert "| latency median | 50.0 µs | 100.0 µs | 2.00 |" in tls


def test_quick_run_writes_the_page_and_the_tutorial_output(tmp_path: Path) -> None:
    out, generated = tmp_path / "results.md", tmp_path / "generated"
    done = subprocess.run(
        [
            sys.executable,
            str(SCRIPT),
            "--quick",
            "--out",
            str(out),
            "--generated",
            str(generated),
            "--json-dir",
            str(tmp_path / "json"),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    page = out.read_text()
    assert page.startswith("# Results")
    assert "## Evaluation runs" in page and "## Benchmarks" in page
    assert "| pf | r1 |" in page
    assert "| decode Odometry |" in page
    assert "Not run" not in page
    printed = (generated / "first-run-output.txt").read_text()
    assert "single: APE after 10 s warm-up" in printed
    assert (generated / "first-run-trajectories.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # --from-json rewrites the same page from those JSON files, running nothing.
    again = subprocess.run(
        [
            sys.executable,
            str(SCRIPT),
            "--quick",
            "--from-json",
            "--out",
            str(tmp_path / "again.md"),
            "--json-dir",
            str(tmp_path / "json"),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert again.returncode == 0, again.stderr
    assert (tmp_path / "again.md").read_text() == page
