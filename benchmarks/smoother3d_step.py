"""The 3D smoother's step on five simulated drones, against the 2D smoother's in the same run.

What is measured
----------------
One *step* of ``kind = "smoother3d"``: every ``STEP_PERIOD`` the window gets a key per robot,
its odometry (a custom factor with the gyro bias), its heights and one range per tag pair (40
for five drones with two tags each), iSAM2 updates, and the estimate is read (the joint
marginal of the latest keys from the Bayes tree). Timed with the localizer's ``step_timer``
(:class:`relloc.localizers.base.Localizer`) on the batches that made a smoother step, after
the start, on ``relloc demo --scenarios drones --bias online``. The window's oldest keys are
marginalised in blocks (``MARGINALISE_EVERY`` of the lag): most steps only add theirs, one in
five re-eliminates the window, so the median and the 90th percentile differ.

The reference, in the same run and interleaved seed by seed: the 2D smoother
(``kind = "smoother"``) on ``tags_odometry`` (five ground robots, two tags each, odometry,
online biases: the same tag pairs in the plane). ``3D / 2D`` says what the third dimension,
the yaws and the gyro biases cost on any machine; the absolute medians are this machine's.

    python benchmarks/smoother3d_step.py                       # seeds 0-2, about a minute
    python benchmarks/smoother3d_step.py --seeds 0 1 2 3 4 --json out/bench/smoother3d.json
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any

from relloc.engine import Engine
from relloc.methods import build_pipeline
from relloc.runs.demo import DemoOptions, scenario_setup


def step_times(scenario: str, seed: int, kind: str) -> list[float]:
    """Seconds of every smoother step (a batch that made an estimate) of one run."""
    sim, config, _ = scenario_setup(scenario, DemoOptions(seed=seed, bias="online"))
    pipeline = build_pipeline("pf", config.with_filter(kind=kind), seed=seed)
    times: list[float] = []
    pipeline.localizer.step_timer = lambda t, seconds, est: (
        times.append(seconds) if est is not None else None
    )
    engine = Engine([pipeline])
    for event in sim.events():
        engine.feed(event)
    engine.finish()
    return times[1:]  # the start is not a step


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    rows: list[dict[str, Any]] = []
    for seed in args.seeds:
        flying = step_times("drones", seed, "smoother3d")
        ground = step_times("tags_odometry", seed, "smoother")
        row = {
            "seed": seed,
            "smoother3d_median_ms": 1000.0 * statistics.median(flying),
            "smoother3d_p90_ms": 1000.0 * statistics.quantiles(flying, n=10)[-1],
            "smoother2d_median_ms": 1000.0 * statistics.median(ground),
            "ratio_3d_2d": statistics.median(flying) / statistics.median(ground),
            "steps": len(flying),
        }
        rows.append(row)
        print(
            f"seed {seed}: smoother3d step median {row['smoother3d_median_ms']:.1f} ms "
            f"(p90 {row['smoother3d_p90_ms']:.1f}), 2D smoother {row['smoother2d_median_ms']:.1f}"
            f" ms, 3D / 2D {row['ratio_3d_2d']:.2f}"
        )
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
