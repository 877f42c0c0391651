"""benchmarks/filter_vs_pfilter.py without pfilter: relloc's timed step reads what a published
estimate carries, and the README figures are written between their markers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from load_file import ROOT, load_module

from relloc.filter.summary import DeferredSummary

bench = load_module(ROOT / "benchmarks" / "filter_vs_pfilter.py", "bench_filter_vs_pfilter")


@pytest.mark.parametrize(
    ("published", "computed"), [(True, {"shape", "distances"}), (False, set())]
)
def test_relloc_step_computes_the_published_summary_only_when_asked(
    published: bool, computed: set[str]
) -> None:
    rng = np.random.default_rng(0)
    scenario = bench.make_scenario(4, rng)
    runner = bench.RellocRunner(
        scenario, bench.starting_cloud(scenario, 300, rng), 0, published=published
    )
    mean = runner.step(scenario.steps[0])
    assert mean.shape == (4, 2)
    summary = runner.pf.last_summary
    assert isinstance(summary, DeferredSummary) and summary.computed == computed


def test_the_figures_replace_only_the_marked_section(tmp_path: Path) -> None:
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{bench.README_BEGIN}\nold figures\n{bench.README_END}\noutro\n")
    results = {
        "400": {"relloc_s": 0.0005, "pfilter_s": 0.0016, "speedup": 3.2},
        "40000": {"relloc_s": 0.012, "pfilter_s": 0.28, "speedup": 23.3},
    }
    bench.write_readme(readme, results, {"400": (40, 40), "40000": (40, 20)}, "context")
    text = readme.read_text()
    assert text.startswith("intro\n") and text.endswith(f"{bench.README_END}\noutro\n")
    assert "old figures" not in text
    assert "| 400 | 0.500 ms | 1.60 ms | 3.2x | 40, 40 |" in text
    assert "| 40 000 | 12.000 ms | 280.00 ms | 23.3x | 40, 20 |" in text


def test_the_phases_time_a_whole_step_and_leave_the_filter_as_a_step_does() -> None:
    rng = np.random.default_rng(1)
    scenario = bench.make_scenario(3, rng)
    cloud = bench.starting_cloud(scenario, 300, rng)
    stepped, timed = (bench.RellocRunner(scenario, cloud, 0) for _ in range(2))
    for s in scenario.steps:
        stepped.step(s)
        phases = timed.phases(s, bench.time.perf_counter)
        assert list(phases) == list(bench.PHASES) and all(v >= 0.0 for v in phases.values())
    # the extra likelihood is kept nowhere, the noise drawn alone comes from a seed of its own
    assert np.array_equal(stepped.pf.particles, timed.pf.particles)
    table = bench.phase_table({"400": phases, "40000": phases}, "context")
    assert "| phase | M = 400 | M = 40 000 |" in table and "| noise draws alone |" in table
