"""Regenerate the real-data tables of docs/results/tiers.md: every shared TIERS bag with a UWB range,
every method, the default seed and the median and range over seeds 0-4.

    .venv/bin/python scripts/tiers_results.py --data ../shared/data --out docs/results/tiers.md

Warm-up windows follow the issue: 5 s for the multi-robot shortbag, 10 s for the pair bags.
"""

from __future__ import annotations

import argparse
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

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


HEADER = (
    "| recording | method | robot | APE median (seed 0) | RMSE (seed 0) | median over seeds | range over seeds |",
    "|---|---|---|---|---|---|---|",
)


def _spread(meds: np.ndarray) -> tuple[float, float, float]:
    """The median, lowest and highest finite value of ``meds`` (NaN when none is finite)."""
    if not np.isfinite(meds).any():
        return math.nan, math.nan, math.nan
    return float(np.nanmedian(meds)), float(np.nanmin(meds)), float(np.nanmax(meds))


def bag_lines(bag: str, per_seed: Sequence[Any]) -> list[str]:
    """The table rows of one recording from its runs' reports (``run_recording``'s), seed 0
    first: per method a row per robot, then the mean over the robots."""
    lines = []
    first = per_seed[0]
    for method in first.methods:  # the requested methods, and multilateration's oracle
        for robot in sorted(first.methods[method].robots):
            meds = np.array([r.methods[method].robots[robot].median for r in per_seed])
            s0 = first.methods[method].robots[robot]
            mos, lo, hi = _spread(meds)
            rng = "–" if not math.isfinite(lo) else f"{lo:.3f}–{hi:.3f}"
            lines.append(
                f"| {bag} | {method} | {robot} | {_fmt(s0.median)} | {_fmt(s0.rmse)} | {_fmt(mos)} | {rng} |"
            )
        mean_seeds = [r.methods[method].mean_ape_median for r in per_seed]
        finite = [m for m in mean_seeds if math.isfinite(m)]
        lines.append(
            f"| {bag} | {method} | **mean** | {_fmt(mean_seeds[0])} | | {_fmt(float(np.median(finite)) if finite else math.nan)} | "
            + (f"{min(finite):.3f}–{max(finite):.3f} |" if finite else "– |")
        )
    return lines


def table(results: Mapping[str, Sequence[Any]]) -> str:
    """The markdown table of every recording's reports, per seed."""
    lines = list(HEADER)
    for bag, per_seed in results.items():
        lines += bag_lines(bag, per_seed)
    return "\n".join(lines) + "\n"


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
    results = {}
    for bag, warmup in BAGS.items():
        config = TeamConfig.load(Path(args.configs) / f"{bag}.toml")
        results[bag] = [
            run_recording(
                Path(args.data) / "tiers" / bag,
                config,
                RunOptions(
                    methods=methods,
                    seed=seed,
                    warmup=warmup,
                    progress=False,
                    models=Path(args.models) if args.models else None,
                ),
            )
            for seed in range(args.seeds)
        ]
    text = table(results)
    print(text)
    if args.out:
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
