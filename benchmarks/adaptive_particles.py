"""Time per update of the sampled filter with the adaptive particle count against the fixed
count, measured in the same process, runs interleaved (a noisy machine slows both alike).

Cases: the TIERS shortbag (if ``../shared/data/tiers`` has it; config
``configs/tiers/multi4_shortbag_20221011.toml``, 50 000 particles at most) and the demo's
``multi`` simulation (20 000 at most). Each localizer step (predict, update, estimate,
resample) is timed alone; the events are read once, before the clock starts. For each case it
prints the median time per update after the warm-up and over the run's last ``--tail`` seconds
(the steady state), for both counts, and their ratio, with the particle count::

    PYTHONPATH=src .venv/bin/python benchmarks/adaptive_particles.py --seeds 0 --repeats 2
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from relloc.config import TeamConfig
from relloc.events import GroundTruthEvent
from relloc.malloc import tune_malloc
from relloc.methods import filter_localizer
from relloc.runs.demo import DemoOptions, scenario_setup

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT.parent / "shared" / "data" / "tiers" / "multi4_shortbag_20221011"
BAG_CONFIG = ROOT / "configs" / "tiers" / "multi4_shortbag_20221011.toml"


def _cases() -> list[tuple[str, TeamConfig, list[Any], float]]:
    """(name, config, events without ground truth, warm-up s)."""
    out = []
    if BAG.exists():
        from relloc.sources.rosbag import RosbagSource

        config = TeamConfig.load(BAG_CONFIG)
        events = [e for e in RosbagSource(BAG, config) if not isinstance(e, GroundTruthEvent)]
        out.append(("shortbag", config, events, 5.0))
    sim, config, _ = scenario_setup("multi", DemoOptions(seed=0))
    out.append(
        (
            "demo multi",
            config,
            [e for e in sim.events() if not isinstance(e, GroundTruthEvent)],
            10.0,
        )
    )
    return out


def _timed_run(
    config: TeamConfig, events: list[Any], seed: int, clock: Any = time.perf_counter
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(time of each step from the first event (s), its duration (s) on ``clock``, particle
    count)."""
    loc = filter_localizer(config, seed=seed)
    t_steps: list[float] = []
    durations: list[float] = []
    counts: list[int] = []
    t0 = events[0].t

    def timed(t: float, seconds: float, out: Any) -> None:
        durations.append(seconds)
        t_steps.append(t - t0)
        counts.append(getattr(loc.filter, "n", 0))

    loc.step_clock = clock
    loc.step_timer = timed
    for ev in events:
        loc.process(ev)
    loc.flush()
    return np.array(t_steps), np.array(durations), np.array(counts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0", help="comma-separated filter seeds")
    ap.add_argument("--repeats", type=int, default=2, help="interleaved runs per count and seed")
    ap.add_argument(
        "--tail", type=float, default=5.0, help="the steady state: the run's last seconds"
    )
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a [filter.adaptive] key for the adaptive runs, e.g. mc_tolerance=0.009 (repeatable)",
    )
    ap.add_argument(
        "--malloc",
        choices=("tuned", "default"),
        default="tuned",
        help="tuned: glibc keeps freed memory mapped, as the relloc command does (relloc.malloc); "
        "default: glibc's own settings",
    )
    ap.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="wall: elapsed time per step; cpu: the thread's CPU time per step (what other jobs "
        "on the machine disturb least)",
    )
    args = ap.parse_args()
    clock = time.perf_counter if args.clock == "wall" else time.thread_time
    if args.malloc == "tuned":
        tune_malloc()
    seeds = [int(s) for s in args.seeds.split(",")]
    results = {}
    changes = {
        k: float(v) if "." in v else int(v) for k, v in (item.split("=", 1) for item in args.set)
    }
    for name, base, events, warmup in _cases():
        fixed_config = base.with_filter(particle_count="fixed")
        config = base.with_filter(**changes)
        rows: dict[str, dict[str, list[float]]] = {"fixed": {}, "adaptive": {}}
        for _ in range(args.repeats):
            for seed in seeds:
                for label, cfg in (("fixed", fixed_config), ("adaptive", config)):
                    t, d, n = _timed_run(cfg, events, seed, clock)
                    end = t[-1]
                    r = rows[label]
                    r.setdefault("after_warmup_ms", []).append(
                        1e3 * float(np.median(d[t >= warmup]))
                    )
                    r.setdefault("tail_ms", []).append(
                        1e3 * float(np.median(d[t >= end - args.tail]))
                    )
                    r.setdefault("count_after_warmup", []).append(float(np.median(n[t >= warmup])))
                    r.setdefault("count_tail", []).append(float(np.median(n[t >= end - args.tail])))
        summary = {
            label: {k: round(statistics.median(v), 3) for k, v in r.items()}
            for label, r in rows.items()
        }
        for k in ("after_warmup_ms", "tail_ms"):
            summary[f"ratio_{k.removesuffix('_ms')}"] = round(
                summary["fixed"][k] / summary["adaptive"][k], 2
            )
        results[name] = summary
        f, a = summary["fixed"], summary["adaptive"]
        print(
            f"{name}: per update after the warm-up {f['after_warmup_ms']:.2f} ms fixed "
            f"({f['count_after_warmup']:.0f}) / {a['after_warmup_ms']:.2f} ms adaptive "
            f"({a['count_after_warmup']:.0f} particles, median): x{summary['ratio_after_warmup']}; "
            f"last {args.tail:g} s {f['tail_ms']:.2f} / {a['tail_ms']:.2f} ms "
            f"({a['count_tail']:.0f} particles): x{summary['ratio_tail']}"
        )
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
