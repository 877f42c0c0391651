"""Run an MRCLAM session with every robot as the reference and tabulate the figures.

    .venv/bin/python scripts/mrclam_references.py --page docs/results/mrclam_references_generated.md
    .venv/bin/python scripts/mrclam_references.py --from-json --page docs/results/mrclam_references_generated.md

Each reference and seed is one ``relloc run DATA --config CONFIG --methods pf --warmup 30
--reference R --seed S --json OUT/R_sS.json`` in a subprocess (``--jobs`` at a time). The
table holds, per run, the worst robot's body-frame APE median, the worst and the median NEES
median over the robots, the lowest and highest 95 % coverage, the filter's restarts (the
``faults`` counters ``inconsistency_restarts`` and ``calibration_restarts``) and the run's wall
time, then the acceptance checks. ``--from-json`` rebuilds the table from ``--out`` without
running anything. Every figure is read from the runs' JSON files.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import statistics
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from relloc.runs.sweep import SweepJob, run_job

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data" / "mrclam" / "MRCLAM_Dataset6"
CONFIG = ROOT / "configs" / "mrclam" / "mrclam.toml"
METHOD = "pf"
WARMUP = 30.0

# The acceptance bounds, for every robot of a run.
BODY_APE_MAX = 0.22
"""Body-frame APE median (m)."""
COVERAGE_RANGE = (0.85, 0.99)
"""Share of the estimates whose 95 % ellipse holds the truth."""
NEES_MAX = 4.0
"""NEES median (2-D position: 2 when the covariance is honest)."""
WALL_MAX = 90.0
"""Wall time of one run (s)."""


@dataclass(frozen=True)
class Row:
    """One run's figures (``None``: absent from its JSON)."""

    reference: str
    seed: int
    body_ape: dict[str, float]
    nees: dict[str, float]
    coverage: dict[str, float]
    inconsistency_restarts: int | None
    calibration_restarts: int | None
    wall_s: float | None
    compute_s: float | None = None
    """The filter's own compute time (``compute_s``): the wall time less start-up and output."""

    @property
    def worst_ape(self) -> tuple[str, float] | None:
        return max(self.body_ape.items(), key=lambda kv: kv[1]) if self.body_ape else None

    @property
    def worst_nees(self) -> float | None:
        return max(self.nees.values()) if self.nees else None

    @property
    def median_nees(self) -> float | None:
        return statistics.median(self.nees.values()) if self.nees else None

    @property
    def coverage_span(self) -> tuple[float, float] | None:
        return (min(self.coverage.values()), max(self.coverage.values())) if self.coverage else None

    def passes(self) -> dict[str, bool]:
        lo, hi = COVERAGE_RANGE
        return {
            "ape": bool(self.body_ape) and all(v <= BODY_APE_MAX for v in self.body_ape.values()),
            "coverage": bool(self.coverage) and all(lo <= v <= hi for v in self.coverage.values()),
            "nees": bool(self.nees) and all(v <= NEES_MAX for v in self.nees.values()),
            "wall": self.wall_s is not None and self.wall_s <= WALL_MAX,
        }


def json_name(reference: str, seed: int) -> str:
    return f"{reference}_s{seed}.json"


def _finite(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def read_row(path: Path, method: str = METHOD) -> Row:
    """The figures of one run's ``--json`` file (the ``run`` entry this script adds: reference,
    seed and wall time; else the scenario's reference and the file's seed)."""
    payload = json.loads(path.read_text())
    (scenario,) = payload["scenarios"].values()
    robots = scenario["methods"][method]["robots"]
    run = payload.get("run", {})

    def figure(key: str) -> dict[str, float]:
        return {name: float(r[key]) for name, r in robots.items() if _finite(r.get(key))}

    faults = scenario.get("faults", {}).get(method, {})
    compute = scenario["methods"][method].get("compute_s")
    return Row(
        reference=run.get("reference", scenario.get("reference", "?")),
        seed=int(run.get("seed", payload.get("seed", 0))),
        body_ape=figure("body_ape_median"),
        nees=figure("nees_median"),
        coverage=figure("coverage95"),
        inconsistency_restarts=faults.get("inconsistency_restarts"),
        calibration_restarts=faults.get("calibration_restarts"),
        wall_s=run.get("wall_s"),
        compute_s=float(compute) if _finite(compute) else None,
    )


def read_rows(folder: Path, method: str = METHOD) -> list[Row]:
    rows = [read_row(p, method) for p in sorted(folder.glob("*.json"))]
    return sorted(rows, key=lambda r: (r.reference, r.seed))


def _f(x: float | None, digits: int) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def _pct(x: float) -> str:
    return f"{100 * x:.0f} %"


def _count(x: int | None) -> str:
    return "–" if x is None else str(x)


def table(rows: list[Row], rule: str | None = None) -> list[str]:
    """The markdown table, a line per run, and the acceptance checks."""
    lo, hi = COVERAGE_RANGE
    out = [
        "| reference | seed | worst body APE median (m) | worst NEES median | median NEES median "
        "| 95 % coverage (lowest–highest) | restarts (inconsistency / calibration) | wall (s) | compute (s) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        worst = r.worst_ape
        ape = "–" if worst is None else f"{worst[1]:.3f} ({worst[0]})"
        span = r.coverage_span
        cov = "–" if span is None else f"{_pct(span[0])}–{_pct(span[1])}"
        name = f"{r.reference} (rule)" if r.reference == rule else r.reference
        out.append(
            f"| {name} | {r.seed} | {ape} | {_f(r.worst_nees, 1)} | {_f(r.median_nees, 1)} | {cov} "
            f"| {_count(r.inconsistency_restarts)} / {_count(r.calibration_restarts)} | {_f(r.wall_s, 0)} | {_f(r.compute_s, 0)} |"
        )
    out += [
        "",
        "Per reference, over its seeds: the worst run's figure (the highest APE and NEES, the "
        "lowest coverage) and the median wall time.",
        "",
        "| reference | seeds | worst body APE median (m) | worst NEES median | lowest 95 % coverage "
        "| restarts (inconsistency / calibration) | median wall (s) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for ref in sorted({r.reference for r in rows}):
        mine = [r for r in rows if r.reference == ref]
        apes = [w[1] for r in mine if (w := r.worst_ape) is not None]
        nees = [n for r in mine if (n := r.worst_nees) is not None]
        covs = [c[0] for r in mine if (c := r.coverage_span) is not None]
        walls = [r.wall_s for r in mine if r.wall_s is not None]
        inc = sum(r.inconsistency_restarts or 0 for r in mine)
        cal = sum(r.calibration_restarts or 0 for r in mine)
        name = f"{ref} (rule)" if ref == rule else ref
        out.append(
            f"| {name} | {len(mine)} | {_f(max(apes) if apes else None, 3)} | {_f(max(nees) if nees else None, 1)} "
            f"| {_pct(min(covs)) if covs else '–'} | {inc} / {cal} "
            f"| {_f(statistics.median(walls) if walls else None, 0)} |"
        )
    checks = [
        ("ape", f"body-frame APE median <= {BODY_APE_MAX:.2f} m for every robot"),
        ("coverage", f"95 % coverage within [{100 * lo:.0f} %, {100 * hi:.0f} %] for every robot"),
        ("nees", f"NEES median <= {NEES_MAX:g} for every robot"),
        ("wall", f"wall time <= {WALL_MAX:.0f} s"),
    ]
    out += ["", "Acceptance checks (per run):", ""]
    for key, text in checks:
        passed = [r for r in rows if r.passes()[key]]
        refs = sorted({r.reference for r in rows})
        every_seed = [
            ref for ref in refs if all(r.passes()[key] for r in rows if r.reference == ref)
        ]
        verdict = "PASS" if len(passed) == len(rows) and rows else "FAIL"
        out.append(
            f"- {verdict}: {text}: {len(passed)} of {len(rows)} runs"
            f" (references passing for every seed: {', '.join(every_seed) or 'none'})"
        )
    return out


def page(
    rows: list[Row], command: str, data: str, config: str, rule: str | None, rebuilt: bool = False
) -> str:
    seeds = sorted({r.seed for r in rows})
    lines = [
        "# MRCLAM: every robot as the reference",
        "",
        "Generated by",
        "",
        "```",
        command,
        "```",
        "",
        (
            "(the table rebuilt from that command's JSON files with `--from-json`; do not edit by hand). "
            if rebuilt
            else "from the runs' JSON files (do not edit by hand). "
        )
        + f"Session `{data}`, config `{config}`, "
        f"method `{METHOD}`, warm-up {WARMUP:.0f} s, seeds {', '.join(map(str, seeds))}; each run is "
        "`relloc run DATA --config CONFIG --methods pf --warmup 30 --reference R --seed S`. "
        "Figures per run over the non-reference robots: the worst body-frame APE median "
        "(in the reference's body frame; the robot in brackets), the worst and the median NEES "
        "median, the lowest and highest 95 % coverage, the filter's restarts and the wall time "
        "of the whole `relloc run` process (`--jobs` of them at once, default 2) beside the filter's "
        "own compute time (`compute_s`).",
        "",
    ]
    if rule is not None:
        lines += [
            f"`(rule)` marks the reference the rule of `relloc.sources.mrclam.choose_reference` gives "
            f"for this session (`python -m relloc.sources.mrclam --reference FOLDER`): {rule}. "
            "See [MRCLAM](../explanation/mrclam.md#the-reference-robot).",
            "",
        ]
    return "\n".join(lines + table(rows, rule)) + "\n"


def run_one(data: Path, config: Path, reference: str, seed: int, out: Path) -> Path:
    """One ``relloc run`` in a subprocess; its JSON gets a ``run`` entry with the wall time."""
    target = out / json_name(reference, seed)
    stem = target.with_suffix("")
    job = SweepJob(
        [
            "run",
            str(data),
            "--config",
            str(config),
            "--methods",
            METHOD,
            "--warmup",
            f"{WARMUP:g}",
            "--reference",
            reference,
            "--seed",
            str(seed),
            "--out",
            str(stem),
            "--no-progress",
        ],
        target,
    )
    result = run_job(job)
    wall = result.wall_s
    stem.with_suffix(".log").write_text(result.stdout + result.stderr)
    if not result.ok:
        raise RuntimeError(
            f"{reference} seed {seed} failed ({result.error}): see {stem.with_suffix('.log')}"
        )
    payload = json.loads(target.read_text())
    payload["run"] = {"reference": reference, "seed": seed, "wall_s": round(wall, 2)}
    target.write_text(json.dumps(payload, indent=2))
    print(f"{reference} seed {seed}: {wall:.0f} s", flush=True)
    return target


def _rule(data: Path) -> str | None:
    try:
        from relloc.sources.mrclam import choose_reference
    except ImportError:
        return None
    try:
        return choose_reference(data)
    except Exception as exc:  # the page still stands without the mark
        print(f"warning: the reference rule failed: {exc}", file=sys.stderr)
        return None


def _shown(path: Path) -> str:
    """``path`` relative to the repository where it is inside it or beside it."""
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        try:
            return str(Path("..") / path.resolve().relative_to(ROOT.parent))
        except ValueError:
            return str(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument(
        "--data", type=Path, default=DATA, help="MRCLAM session folder (default: Dataset 6)"
    )
    parser.add_argument(
        "--config",
        type=Path,
        default=CONFIG,
        help="team config (default: configs/mrclam/mrclam.toml)",
    )
    parser.add_argument(
        "--seeds", type=int, nargs="+", default=None, help="default: 0 1 2 (with --from-json: all)"
    )
    parser.add_argument(
        "--references", nargs="+", default=None, help="default: every robot of the config"
    )
    parser.add_argument("--jobs", type=int, default=2, help="runs at once (default 2)")
    parser.add_argument(
        "--out", type=Path, default=ROOT / "out" / "mrclam_references", help="folder for the JSON"
    )
    parser.add_argument("--page", type=Path, default=None, help="write the markdown page here")
    parser.add_argument(
        "--from-json", action="store_true", help="rebuild from --out's JSON, run nothing"
    )
    parser.add_argument(
        "--skip-missing", action="store_true", help="exit 0 with a note when --data is absent"
    )
    args = parser.parse_args(argv)
    given = [a for a in (sys.argv[1:] if argv is None else argv) if a != "--from-json"]
    command = shlex.join(["python", "scripts/mrclam_references.py", *given])

    if not args.from_json:
        if not args.data.is_dir():
            print(f"{args.data}: no MRCLAM session there", file=sys.stderr)
            return 0 if args.skip_missing else 2
        references = args.references
        if references is None:
            from relloc.config import TeamConfig

            references = list(TeamConfig.load(args.config).robot_names)
        args.out.mkdir(parents=True, exist_ok=True)
        jobs = [(ref, seed) for ref in references for seed in (args.seeds or [0, 1, 2])]
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            futures = [
                pool.submit(run_one, args.data, args.config, ref, seed, args.out)
                for ref, seed in jobs
            ]
            paths = [f.result() for f in futures]
        rows = sorted((read_row(p) for p in paths), key=lambda r: (r.reference, r.seed))
    else:
        rows = read_rows(args.out)
        if args.references:
            rows = [r for r in rows if r.reference in args.references]
        if args.seeds:
            rows = [r for r in rows if r.seed in args.seeds]
        if not rows:
            print(f"{args.out}: no run JSON", file=sys.stderr)
            return 2
    rule = _rule(args.data) if args.data.is_dir() else None
    text = page(rows, command, _shown(args.data), _shown(args.config), rule, args.from_json)
    print(text)
    if args.page is not None:
        args.page.parent.mkdir(parents=True, exist_ok=True)
        args.page.write_text(text)
        print(f"written to {args.page}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
