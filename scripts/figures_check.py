"""Run the figures that a refactor must leave unchanged and write each run's JSON to one folder.

    .venv/bin/python scripts/figures_check.py --out out/figures-before
    .venv/bin/python scripts/figures_check.py --out out/figures-after --compare out/figures-before

The runs (``relloc.evaluation.pages.figure_runs``): `relloc demo --seed 0`, the self-calibration
demo, the TIERS shortbag seeds 0-4, `pair_range` with calibrated and online biases, the static
seven-robot team `case4_test1_static` (the smoother) and MRCLAM Dataset 6. Wall and compute times
are dropped before comparing; every other field, and every TUM trajectory file byte for byte, must
be equal.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from relloc.evaluation.pages import figure_runs
from relloc.runs.sweep import SweepJob, SweepResult, run_jobs

TIMING_KEYS = {"compute_s", "wall_s", "elapsed_s", "cpu_s", "seconds"}


def strip(value: object) -> object:
    if isinstance(value, dict):
        return {k: strip(v) for k, v in value.items() if k not in TIMING_KEYS}
    if isinstance(value, list):
        return [strip(v) for v in value]
    return value


def job(name: str, argv: list[str], out: Path) -> SweepJob:
    return SweepJob([*argv, "--no-progress", "--out", str(out / name)], out / f"{name}.json", name)


def line(result: SweepResult) -> str:
    if result.ok:
        return f"{result.job.label}: ok"
    return f"{result.job.label}: {result.error}\n{result.stderr[-2000:]}"


def compare(a: Path, b: Path) -> int:
    bad = 0
    for path in sorted(a.glob("*.json")):
        other = b / path.name
        if not other.exists():
            print(f"{path.stem}: missing in {b}")
            bad += 1
            continue
        same = strip(json.loads(path.read_text())) == strip(json.loads(other.read_text()))
        tum = sorted((a / path.stem).glob("**/*.txt"))
        differ = [
            t.name
            for t in tum
            if not (b / t.relative_to(a)).exists()
            or t.read_bytes() != (b / t.relative_to(a)).read_bytes()
        ]
        same = same and not differ
        detail = (
            f" (TUM files differ: {', '.join(differ)})" if differ else f" ({len(tum)} TUM files)"
        )
        print(f"{path.stem}: {'identical' if same else 'DIFFERENT'}{detail}")
        bad += not same
    return bad


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data"))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--compare", type=Path, default=None, help="a folder of an earlier run")
    parser.add_argument("--only", default=None, help="comma-separated run names")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    table = figure_runs(args.data)
    if args.only:
        table = {k: v for k, v in table.items() if k in args.only.split(",")}
    for result in run_jobs([job(*kv, args.out) for kv in table.items()], args.jobs):
        print(line(result), flush=True)
    if args.compare is not None:
        sys.exit(1 if compare(args.compare, args.out) else 0)


if __name__ == "__main__":
    main()
