"""Every filter kind on the recordings and scenarios that tell them apart; the table of
docs/results/filter_kinds_generated.md.

    .venv/bin/python scripts/filter_kinds.py --page docs/results/filter_kinds_generated.md
    .venv/bin/python scripts/filter_kinds.py --from-json --page docs/results/filter_kinds_generated.md

Each cell is one ``relloc run`` (a recording) or ``relloc demo`` (a simulated scenario) with
``--methods pf --filter-kind K --json``, a subprocess of ``relloc.runs.sweep.run_job``;
multilateration is run once per row.
The figure of a robot is its APE median after one rotation/reflection for the run, the
alignment relloc gives multilateration (where the orientation was unobservable, its published
shapes' APE aligned the same way). A cell gives the mean over the robots / the worst robot, the
lowest 95 % coverage of the published covariance and how many robots are at most
multilateration's. ``auto`` names the kind it chose. Recordings
come from ``../shared/data``; a row whose data is absent is left out. ``--from-json`` rebuilds
the page from ``--out`` without running anything.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomlkit

from relloc.runs.sweep import SweepJob, SweepResult, run_job

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"
KINDS = ("particle", "gaussian_sum", "range_graph", "smoother", "auto")
TIMEOUT = 600.0
"""Seconds one run may take before its cell says so."""


@dataclass(frozen=True)
class Row:
    """One recording or scenario: how to run it, and what it needs."""

    name: str
    what: str
    args: tuple[str, ...]
    """``relloc`` arguments before ``--methods``."""
    needs: Path | None = None
    calibrate: tuple[str, ...] = ()
    """``relloc calibrate`` arguments run first (writes ``{out}/<name>.toml``)."""
    kinds: tuple[str, ...] = KINDS
    multilateration: bool = True
    """Whether to run multilateration (no figure to compare on some recordings)."""
    kind_args: tuple[tuple[str, tuple[str, ...]], ...] = ()
    """Extra arguments of some kinds' runs (modes a kind needs), as ``(kind, args)``."""


def _no_odometry(config: Path, out: Path) -> Path:
    """``config`` with every robot's ``odom_topic`` removed, written into ``out``."""
    doc = tomlkit.parse(config.read_text())
    for robot in doc["robots"]:  # type: ignore[union-attr]
        robot.pop("odom_topic", None)
    path = out / f"{config.stem}_no_odometry.toml"
    path.write_text(tomlkit.dumps(doc))
    return path


def rows(out: Path) -> list[Row]:
    tiers = DATA / "tiers"
    shortbag = tiers / "multi4_shortbag_20221011"
    pair = tiers / "pair_range_20220907_1725"
    static = DATA / "tiers_uwb_rel" / "case4_test1_static"
    sb_config = ROOT / "configs" / "tiers" / "multi4_shortbag_20221011.toml"
    out.mkdir(parents=True, exist_ok=True)
    no_odom = _no_odometry(sb_config, out) if sb_config.exists() else sb_config
    static_cal = out / "case4_calibrated.toml"
    mrclam = DATA / "mrclam" / "MRCLAM_Dataset6"
    grid20 = ("demo", "--scenarios", "grid", "--robots", "20")
    grid50 = ("demo", "--scenarios", "grid", "--robots", "50")
    return [
        Row(
            "shortbag_no_odometry",
            "shortbag, odometry topics left out (4 robots, two drive)",
            ("run", str(shortbag), "--config", str(no_odom)),
            shortbag,
        ),
        Row(
            "shortbag",
            "shortbag as shipped (odometry, compass)",
            ("run", str(shortbag), "--config", str(sb_config)),
            shortbag,
        ),
        Row(
            "pair_range",
            "pair_range as shipped (two robots, one range)",
            (
                "run",
                str(pair),
                "--config",
                str(ROOT / "configs" / "tiers" / "pair_range_20220907_1725.toml"),
            ),
            pair,
        ),
        Row(
            "case4_static",
            "seven robots standing still, no odometry; biases from the first 17 s, scored on the rest",
            ("run", str(static), "--config", str(static_cal), "--span", "17:"),
            static,
            calibrate=(
                "calibrate",
                str(static),
                "--config",
                str(ROOT / "configs" / "tiers_uwb_rel" / "case4.toml"),
                "--span",
                ":17",
                "--write",
                str(static_cal),
            ),
        ),
        Row("multi", "simulator: the demo's five robots", ("demo", "--scenarios", "multi")),
        Row(
            "mrclam",
            "MRCLAM Dataset 6 as shipped (odometry, camera sightings, headings estimated; "
            "the smoother with compass headings and fixed scales, as it needs)",
            (
                "run",
                str(mrclam),
                "--config",
                str(ROOT / "configs" / "mrclam" / "dataset6.toml"),
                "--warmup",
                "30",
            ),
            mrclam,
            multilateration=False,
            kind_args=(("smoother", ("--heading", "compass", "--odom-scale", "fixed")),),
        ),
        Row(
            "grid20",
            "simulator: grid of 20 robots, all driving",
            grid20,
            kinds=("range_graph", "smoother", "auto"),
        ),
        Row(
            "grid20_seed1", "the same, seed 1", (*grid20, "--seed", "1"), kinds=("smoother", "auto")
        ),
        Row(
            "grid20_seed2", "the same, seed 2", (*grid20, "--seed", "2"), kinds=("smoother", "auto")
        ),
        Row(
            "grid50",
            "simulator: grid of 50 robots, all driving",
            grid50,
            kinds=("range_graph", "smoother", "auto"),
        ),
        Row("grid50_seed1", "the same, seed 1", (*grid50, "--seed", "1"), kinds=("smoother",)),
        Row("grid50_seed2", "the same, seed 2", (*grid50, "--seed", "2"), kinds=("smoother",)),
    ]


def _json(out: Path, row: Row, kind: str) -> Path:
    return out / f"{row.name}__{kind}.json"


def job(row: Row, kind: str, out: Path) -> SweepJob:
    """The ``relloc`` run of one cell (``relloc.runs.sweep`` adds ``--json``)."""
    method = "multilateration" if kind == "multilateration" else "pf"
    argv = [*row.args, "--methods", method, "--no-progress"]
    argv += ["--out", str(out / "plots" / f"{row.name}__{kind}")]
    if kind != "multilateration":
        argv += ["--filter-kind", kind, *dict(row.kind_args).get(kind, ())]
    return SweepJob(argv, _json(out, row, kind), cwd=ROOT, timeout=TIMEOUT)


def cell_payload(result: SweepResult, kind: str) -> dict[str, Any]:
    """One run's figures plus ``wall_s`` and the chosen kind, or ``{"error": ...}``, written back
    to its JSON path."""
    if result.payload is None:
        if result.returncode is None:
            reason = f"over {TIMEOUT:.0f} s"
        else:
            reason = (result.stderr.strip().splitlines() or [result.error or "failed"])[-1]
        payload: dict[str, Any] = {"error": reason}
    else:
        payload = result.payload
        chosen = re.search(r"filter: (\w+) \(kind", result.stdout)
        payload["run"] = {"wall_s": result.wall_s, "kind": chosen.group(1) if chosen else kind}
    result.job.json_path.write_text(json.dumps(payload, indent=1))
    return payload


def run_cell(row: Row, kind: str, out: Path) -> dict[str, Any]:
    """One run; its JSON path gets the figures plus ``wall_s`` and the chosen kind."""
    return cell_payload(run_job(job(row, kind, out)), kind)


def robot_figure(robot: dict[str, Any]) -> Any:
    """The figure of one robot: its shape APE where the orientation was unobservable, else its
    APE under one rotation/reflection for the run (multilateration's own alignment)."""
    return robot.get(
        "shape_ape_median", robot.get("run_aligned_ape_median", robot.get("ape_median"))
    )


def robots(payload: dict[str, Any]) -> dict[str, dict[str, Any]] | str:
    """Each robot's JSON figures of one run (its filter's, else multilateration's), or its error."""
    if "error" in payload:
        return str(payload["error"])
    (scenario,) = payload["scenarios"].values()
    methods = scenario["methods"]
    return dict((methods.get("pf") or methods["multilateration"])["robots"])


def cell(payload: dict[str, Any] | None, baseline: dict[str, Any] | None = None) -> str:
    """Mean / worst robot, the lowest coverage, and how many robots are at most ``baseline``'s."""
    if payload is None:
        return "–"
    found = robots(payload)
    if isinstance(found, str):
        return f"({found.split('error: ')[-1].split(' (')[0][:70]})"
    figures = {r: robot_figure(v) for r, v in found.items()}
    values = {r: v for r, v in figures.items() if isinstance(v, float)}
    if not values:
        return "(no estimate)"
    text = f"{sum(values.values()) / len(values):.2f} / {max(values.values()):.2f}"
    covs = [v["coverage95"] for v in found.values() if isinstance(v.get("coverage95"), float)]
    if covs and math.isfinite(min(covs)):
        text += f", {100 * min(covs):.0f} %"
    ref = robots(baseline) if baseline is not None else None
    base = {r: robot_figure(v) for r, v in ref.items()} if isinstance(ref, dict) else {}
    if any(isinstance(v, float) for v in base.values()):
        held = [r for r, v in values.items() if isinstance(base.get(r), float) and v <= base[r]]
        text += f", {len(held)}/{len(values)} ≤ m."
    return text


def page(table_rows: list[tuple[Row, dict[str, dict[str, Any]]]], command: str) -> str:
    lines = [
        "# Filter kinds side by side",
        "",
        f"Generated by `{command}` (scripts/filter_kinds.py); every figure is read from the runs' JSON.",
        "",
        "Per cell: the mean over the robots / the worst robot of the APE median (m) after one",
        "rotation/reflection for the run, as multilateration is aligned (for estimates whose",
        "orientation was unobservable, their published shapes'), then the lowest 95 % coverage of",
        "the published covariance over the robots, then how many robots are at most",
        "multilateration's (`≤ m.`). Multilateration has no covariance. `auto` names the kind it",
        "chose. Seed 0 unless the row says otherwise.",
        "",
        "| recording | " + " | ".join(KINDS) + " | multilateration |",
        "| --- |" + " --- |" * (len(KINDS) + 1),
    ]
    for row, cells in table_rows:
        parts = []
        for kind in KINDS:
            payload = cells.get(kind)
            text = cell(payload, cells.get("multilateration"))
            if kind == "auto" and payload is not None and "run" in payload:
                text = f"{payload['run']['kind']}: {text}"
            parts.append(text)
        parts.append(cell(cells.get("multilateration")))
        lines.append(f"| {row.what} | " + " | ".join(parts) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out", type=Path, default=ROOT / "out" / "filter_kinds", help="the runs' JSON files"
    )
    parser.add_argument("--page", type=Path, default=None, help="write the markdown page here")
    parser.add_argument(
        "--from-json", action="store_true", help="rebuild from --out without running"
    )
    parser.add_argument("--only", default=None, help="comma-separated row names")
    args = parser.parse_args(argv)
    wanted = set(args.only.split(",")) if args.only else None
    table_rows = []
    for row in rows(args.out):
        if wanted is not None and row.name not in wanted:
            continue
        if row.needs is not None and not row.needs.exists():
            print(f"{row.name}: {row.needs} absent, left out", file=sys.stderr)
            continue
        cells: dict[str, dict[str, Any]] = {}
        if not args.from_json and row.calibrate:
            subprocess.run(
                [sys.executable, "-m", "relloc.cli", *row.calibrate],
                cwd=ROOT,
                check=True,
                capture_output=True,
                timeout=TIMEOUT,
            )
        for kind in (*row.kinds, *(("multilateration",) if row.multilateration else ())):
            path = _json(args.out, row, kind)
            if args.from_json:
                if path.exists():
                    cells[kind] = json.loads(path.read_text())
                continue
            cells[kind] = run_cell(row, kind, args.out)
            print(f"{row.name} {kind}: {cell(cells[kind])}", file=sys.stderr, flush=True)
        table_rows.append((row, cells))
    text = page(
        table_rows, "python scripts/filter_kinds.py" + (" --from-json" if args.from_json else "")
    )
    if args.page is not None:
        args.page.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
