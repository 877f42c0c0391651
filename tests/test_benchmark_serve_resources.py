"""benchmarks/serve_resources.py: its options, and the latency percentiles of relloc.live.resources
(no server started)."""

from __future__ import annotations

import pytest
from load_file import ROOT, load_module

from relloc.live.resources import percentiles

bench = load_module(ROOT / "benchmarks" / "serve_resources.py", "bench_serve_resources")


def test_percentiles_in_milliseconds() -> None:
    out = percentiles([0.001 * k for k in range(1, 21)])
    assert out == {"p50_ms": 10.5, "p95_ms": 19.0, "max_ms": 20.0, "n": 20}
    assert percentiles([])["n"] == 0


def test_defaults_and_bad_particles(capsys: pytest.CaptureFixture[str]) -> None:
    args = bench._parser().parse_args([])
    assert (args.particles, args.scenarios, args.sim_duration) == ("default", "sim5,shortbag", 30.0)
    assert bench.main(["--particles", "many", "--scenarios", "sim5"]) == 2
    assert "--particles must be" in capsys.readouterr().err
