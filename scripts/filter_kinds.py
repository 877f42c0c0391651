"""Every filter kind on the recordings and scenarios that tell them apart; the table of
docs/filter_kinds_generated.md.

    .venv/bin/python scripts/filter_kinds.py --page docs/filter_kinds_generated.md
    .venv/bin/python scripts/filter_kinds.py --from-json --page docs/filter_kinds_generated.md

Each cell is one ``relloc run`` (a recording) or ``relloc demo`` (a simulated scenario) with
``--methods pf --filter-kind K --json`` in a subprocess; multilateration is run once per row.
The figure of a robot is its shape APE median (one rotation/reflection for the run) where the
run found the orientation unobservable, else its APE median; multilateration's is aligned once
per run, as relloc reports it. A cell gives the mean over the robots / the worst robot, and the
lowest 95 % coverage of the published covariance. ``auto`` names the kind it chose. Recordings
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
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomlkit

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
    """Whether to run multilateration (9 minutes alone at 50 robots)."""


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
    return [
        Row("shortbag_no_odometry", "shortbag, odometry topics left out (4 robots, two drive)",
            ("run", str(shortbag), "--config", str(no_odom)), shortbag),
        Row("shortbag", "shortbag as shipped (odometry, compass)",
            ("run", str(shortbag), "--config", str(sb_config)), shortbag),
        Row("pair_range", "pair_range as shipped (two robots, one range)",
            ("run", str(pair), "--config", str(ROOT / "configs" / "tiers" / "pair_range_20220907_1725.toml")), pair),
        Row("case4_static", "seven robots standing still, no odometry; biases from the first 17 s, scored on the rest",
            ("run", str(static), "--config", str(static_cal), "--span", "17:"), static,
            calibrate=("calibrate", str(static), "--config", str(ROOT / "configs" / "tiers_uwb_rel" / "case4.toml"),
                       "--span", ":17", "--write", str(static_cal))),
        Row("multi", "simulator: the demo's five robots", ("demo", "--scenarios", "multi")),
        Row("grid20", "simulator: grid of 20 robots, all driving", ("demo", "--scenarios", "grid", "--robots", "20"),
            kinds=("range_graph", "smoother", "auto")),
        Row("grid50", "simulator: grid of 50 robots, all driving (multilateration not run: 9 min)",
            ("demo", "--scenarios", "grid", "--robots", "50"), kinds=("range_graph", "smoother", "auto"),
            multilateration=False),
    ]


def _json(out: Path, row: Row, kind: str) -> Path:
    return out / f"{row.name}__{kind}.json"


def run_cell(row: Row, kind: str, out: Path) -> dict[str, Any]:
    """One run; its JSON path gets the figures plus ``wall_s`` and the chosen kind."""
    path = _json(out, row, kind)
    method = "multilateration" if kind == "multilateration" else "pf"
    cmd = [sys.executable, "-m", "relloc.cli", *row.args, "--methods", method, "--no-progress",
           "--json", str(path), "--out", str(out / "plots" / f"{row.name}__{kind}")]
    if kind != "multilateration":
        cmd += ["--filter-kind", kind]
    start = time.perf_counter()
    try:
        done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        path.write_text(json.dumps({"error": f"over {TIMEOUT:.0f} s"}))
        return json.loads(path.read_text())
    wall = time.perf_counter() - start
    if done.returncode != 0:
        path.write_text(json.dumps({"error": (done.stderr.strip().splitlines() or ["failed"])[-1]}))
        return json.loads(path.read_text())
    payload = json.loads(path.read_text())
    chosen = re.search(r"filter: (\w+) \(kind", done.stdout)
    payload["run"] = {"wall_s": wall, "kind": chosen.group(1) if chosen else kind}
    path.write_text(json.dumps(payload, indent=1))
    return payload


def robot_figure(robot: dict[str, Any]) -> Any:
    """The figure of one robot: its shape APE where the orientation was unobservable, else its
    APE under one rotation/reflection for the run (multilateration's own alignment)."""
    return robot.get("shape_ape_median", robot.get("run_aligned_ape_median", robot.get("ape_median")))


def figures(payload: dict[str, Any]) -> tuple[float, float, float | None] | str:
    """(mean over robots, worst robot, lowest coverage) of one run, or its error."""
    if "error" in payload:
        return str(payload["error"])
    (scenario,) = payload["scenarios"].values()
    methods = scenario["methods"]
    method = methods.get("pf") or methods["multilateration"]
    values = [robot_figure(r) for r in method["robots"].values()]
    per_robot = [v for v in values if isinstance(v, float)]
    if not per_robot:
        return "no estimate"
    covs = [r["coverage95"] for r in method["robots"].values() if isinstance(r.get("coverage95"), float)]
    return sum(per_robot) / len(per_robot), max(per_robot), (min(covs) if covs else None)


def cell(payload: dict[str, Any] | None) -> str:
    if payload is None:
        return "–"
    f = figures(payload)
    if isinstance(f, str):
        return f"({f[:40]})"
    mean, worst, cov = f
    text = f"{mean:.2f} / {worst:.2f}"
    if cov is not None and math.isfinite(cov):
        text += f", {100 * cov:.0f} %"
    return text


def page(table_rows: list[tuple[Row, dict[str, dict[str, Any]]]], command: str) -> str:
    lines = [
        "# Filter kinds side by side",
        "",
        f"Generated by `{command}` (scripts/filter_kinds.py); every figure is read from the runs' JSON.",
        "",
        "Per cell: the mean over the robots / the worst robot of the APE median (m; the shape APE",
        "after one rotation/reflection for the run where the orientation is unobservable), then the",
        "lowest 95 % coverage of the published covariance over the robots. Multilateration has no",
        "covariance. `auto` names the kind it chose. Seed 0 everywhere.",
        "",
        "| recording | " + " | ".join(KINDS) + " | multilateration |",
        "| --- |" + " --- |" * (len(KINDS) + 1),
    ]
    for row, cells in table_rows:
        parts = []
        for kind in KINDS:
            payload = cells.get(kind)
            text = cell(payload)
            if kind == "auto" and payload is not None and "run" in payload:
                text = f"{payload['run']['kind']}: {text}"
            parts.append(text)
        parts.append(cell(cells.get("multilateration")))
        lines.append(f"| {row.what} | " + " | ".join(parts) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "filter_kinds", help="the runs' JSON files")
    parser.add_argument("--page", type=Path, default=None, help="write the markdown page here")
    parser.add_argument("--from-json", action="store_true", help="rebuild from --out without running")
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
            subprocess.run([sys.executable, "-m", "relloc.cli", *row.calibrate], cwd=ROOT, check=True,
                           capture_output=True, timeout=TIMEOUT)
        for kind in (*row.kinds, *(("multilateration",) if row.multilateration else ())):
            path = _json(args.out, row, kind)
            if args.from_json:
                if path.exists():
                    cells[kind] = json.loads(path.read_text())
                continue
            cells[kind] = run_cell(row, kind, args.out)
            print(f"{row.name} {kind}: {cell(cells[kind])}", file=sys.stderr, flush=True)
        table_rows.append((row, cells))
    text = page(table_rows, "python scripts/filter_kinds.py" + (" --from-json" if args.from_json else ""))
    if args.page is not None:
        args.page.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
