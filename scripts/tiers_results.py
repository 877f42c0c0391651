"""Regenerate the real-data tables of docs/results/tiers.md: every shared TIERS bag with a UWB range,
every method, the default seed and the median and range over seeds 0-4.

    .venv/bin/python scripts/tiers_results.py --data ../shared/data --out docs/results/tiers.md

Warm-up windows follow the issue: 5 s for the multi-robot shortbag, 10 s for the pair bags.
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

import numpy as np

from relloc.config import TeamConfig
from relloc.runs.recording import RunOptions, run_recording

BAGS = {
    "multi4_shortbag_20221011": 5.0,
    "pair_range_20220907_1725": 10.0,
    "pair_chair_moving_20220923": 10.0,
}
METHODS = ("pf", "multilateration")


def _fmt(x: float) -> str:
    return "–" if not math.isfinite(x) else f"{x:.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="../shared/data")
    parser.add_argument("--configs", default="configs/tiers")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--models", default=None)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    methods = tuple(args.methods.split(","))
    lines = [
        "| recording | method | robot | APE median (seed 0) | RMSE (seed 0) | median over seeds | range over seeds |",
        "|---|---|---|---|---|---|---|",
    ]
    for bag, warmup in BAGS.items():
        config = TeamConfig.load(Path(args.configs) / f"{bag}.toml")
        per_seed = []
        for seed in range(args.seeds):
            opts = RunOptions(
                methods=methods,
                seed=seed,
                warmup=warmup,
                progress=False,
                models=Path(args.models) if args.models else None,
            )
            per_seed.append(run_recording(Path(args.data) / "tiers" / bag, config, opts))
        first = per_seed[0]
        for method in first.methods:  # the requested methods, and multilateration's oracle
            robots = sorted(first.methods[method].robots)
            rows = []
            for robot in robots:
                meds = np.array([r.methods[method].robots[robot].median for r in per_seed])
                s0 = first.methods[method].robots[robot]
                rows.append(
                    (
                        robot,
                        s0.median,
                        s0.rmse,
                        np.nanmedian(meds) if np.isfinite(meds).any() else math.nan,
                        np.nanmin(meds) if np.isfinite(meds).any() else math.nan,
                        np.nanmax(meds) if np.isfinite(meds).any() else math.nan,
                    )
                )
            for robot, med, rmse, mos, lo, hi in rows:
                rng = "–" if not math.isfinite(lo) else f"{lo:.3f}–{hi:.3f}"
                lines.append(
                    f"| {bag} | {method} | {robot} | {_fmt(med)} | {_fmt(rmse)} | {_fmt(mos)} | {rng} |"
                )
            means = [first.methods[method].mean_ape_median]
            mean_seeds = [r.methods[method].mean_ape_median for r in per_seed]
            finite = [m for m in mean_seeds if math.isfinite(m)]
            lines.append(
                f"| {bag} | {method} | **mean** | {_fmt(means[0])} | | {_fmt(float(np.median(finite)) if finite else math.nan)} | "
                + (f"{min(finite):.3f}–{max(finite):.3f} |" if finite else "– |")
            )
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
