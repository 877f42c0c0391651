"""The engine's CPU on the same events fed at once and paced by their stamps.

``relloc serve`` runs the engine ``relloc run`` runs, yet a second of live data costs it more
CPU than the same second offline: between two batches the server's thread sleeps, and a thread
that slept runs its next batch on cold caches. This feeds the same events (``sim5``, the five
simulated robots ``serve_vs_subscriber.py`` publishes) to the same engine as serve builds it
(its filter step, its bounded memory, no shape unless asked), alternately:

* ``tight``: every event at once, in a loop (what ``relloc run`` does);
* ``paced``: each event at its stamp in real time, the thread sleeping until the next filter
  batch is due and handling what arrived meanwhile at once, as serve's engine thread wakes
  for a batch.

Each run starts from a fresh engine, converged by the first ``--settle`` s fed at once; the rest
is timed by the thread's CPU clock, per second of data. Runs alternate which goes first
(``--repeats`` pairs); the ratio of the medians is what pacing alone costs::

    .venv/bin/python benchmarks/paced_engine.py [--duration 30] [--settle 10] [--repeats 3] [--json F]

``RELLOC_COMPILED=1`` measures the compiled step, as it does for serve.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from relloc.engine import Engine
from relloc.events import Event, GroundTruthEvent
from relloc.filter import compiled
from relloc.live.publish import simulated_team
from relloc.malloc import tune_malloc
from relloc.methods import build_pipeline

BATCH = 0.1
"""Seconds between two wakes of the paced thread: the filter's batch period."""


def run_once(
    events: list[Event], config: Any, seed: int, settle: float, paced: bool
) -> tuple[float, Engine]:
    """Thread CPU seconds per second of data after ``settle``, fed at once or paced (the same
    estimates either way), and the engine."""
    pipeline = build_pipeline("pf", config, seed=seed)
    pipeline.localizer.keeps_run = False
    pipeline.localizer.shape_wanted = False
    engine = Engine([pipeline], keep_estimates=50)
    t0 = events[0].t + settle
    timed = [e for e in events if e.t >= t0]
    for e in events:
        if e.t >= t0:
            break
        engine.feed(e)
    wall0, cpu0, due = time.monotonic(), time.thread_time(), t0
    for e in timed:
        if paced and e.t >= due:
            time.sleep(max(0.0, wall0 + (e.t - t0) - time.monotonic()))
            due = e.t + BATCH
        engine.feed(e)
    return (time.thread_time() - cpu0) / (timed[-1].t - t0), engine


def measure(duration: float, settle: float, repeats: int, seed: int) -> dict[str, Any]:
    """Both ways, ``repeats`` times each, alternating which runs first."""
    sim, config = simulated_team(seed, duration)
    events = [e for e in sim.events() if not isinstance(e, GroundTruthEvent)]
    runs: dict[str, list[float]] = {"tight": [], "paced": []}
    with compiled.chosen(compiled.serve_default()):
        for k in range(repeats):
            order = ("tight", "paced") if k % 2 == 0 else ("paced", "tight")
            for mode in order:
                cpu, _ = run_once(events, config, seed, settle, mode == "paced")
                runs[mode].append(cpu)
    tight, paced = (statistics.median(runs[m]) for m in ("tight", "paced"))
    return {
        "step": "compiled" if compiled.serve_default() else "NumPy",
        "events": len(events),
        "tight_cpu_percent": round(100 * tight, 2),
        "paced_cpu_percent": round(100 * paced, 2),
        "ratio": round(paced / tight, 2),
        "runs_cpu_percent": {m: [round(100 * v, 2) for v in vs] for m, vs in runs.items()},
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=30.0, help="simulated seconds")
    p.add_argument("--settle", type=float, default=10.0, help="seconds fed at once first")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", dest="json_path", type=Path, default=None, metavar="FILE")
    args = p.parse_args(argv)
    if args.settle >= args.duration:
        raise SystemExit("--settle must be shorter than --duration")
    tune_malloc()
    out = measure(args.duration, args.settle, args.repeats, args.seed)
    out["cpus"] = os.cpu_count()
    print(
        f"sim5, {out['step']} step: {out['tight_cpu_percent']} % of a core fed at once, "
        f"{out['paced_cpu_percent']} % paced by the stamps ({out['ratio']}x); "
        f"runs {out['runs_cpu_percent']}"
    )
    if args.json_path is not None:
        args.json_path.parent.mkdir(parents=True, exist_ok=True)
        args.json_path.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
