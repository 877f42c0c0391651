"""benchmarks/paced_engine.py: the paced run feeds the engine the same events in real time and
gets the same estimates as the run fed at once, so the two differ only by how the CPU runs."""

from __future__ import annotations

import time

from load_file import ROOT, load_module

from relloc.events import GroundTruthEvent
from relloc.live.publish import simulated_team

bench = load_module(ROOT / "benchmarks" / "paced_engine.py", "bench_paced")


def test_pacing_takes_the_data_time_and_changes_no_estimate() -> None:
    sim, config = simulated_team(0, 5.0)
    events = [e for e in sim.events() if not isinstance(e, GroundTruthEvent)]
    cpu_tight, tight = bench.run_once(events, config, 0, 3.0, paced=False)
    start = time.monotonic()
    cpu_paced, paced = bench.run_once(events, config, 0, 3.0, paced=True)
    assert time.monotonic() - start >= events[-1].t - events[0].t - 3.0 - bench.BATCH
    a, b = tight.pipelines[0].estimates, paced.pipelines[0].estimates
    assert len(a) == len(b) >= 10
    assert [(e.t, e.positions) for e in a] == [(e.t, e.positions) for e in b]
    assert cpu_tight > 0.0 and cpu_paced > 0.0
