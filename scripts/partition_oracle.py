"""What cutting one robot off must move, offline: the grid team's onboard views with and
without that robot's messages for a while, in header order (no transport, no arrival order).

``benchmarks/onboard.py`` cuts a robot from the team's network and asks two things of the live
serves: the other robots' views of each other stay within 0.02 m of those of the run without
the cut (``partition_shift_m``), and the cut robot's views are back soon after it. Here the same
cut runs offline, where nothing but the cut can move an estimate. Each uncut robot's filter (it
as the reference, as ``relloc serve --robot`` runs it) runs with and without the cut robot's own
messages (:func:`relloc.events.measured_by`: its odometry, the ranges its node measures) from
``--start`` to ``--end``; the cut robot's filter runs with and without everyone else's. Same
seed, same events otherwise. Per filter kind and simulator condition
(``scripts/onboard_view_oracle.py``'s), over the seeds:

* ``shift``: the largest (median) distance during the cut between an uncut robot's view of
  another uncut robot with and without the cut: what the information of the cut robot's
  messages is worth to the others' views of each other;
* ``two seeds``: the same between two runs without a cut, ``SEED_STEP`` seeds apart: the
  filter's own spread (zero for a deterministic filter);
* ``back after``: seconds after ``--end`` until the cut robot's views stay within ``--tol`` m of
  those of the run without the cut to the end of the run (median and range over the seeds;
  ``never``: not before the end).

Positions are compared in the filter's frame: the body frame turns both runs by the viewer's
same odometry yaw, so the distances are those of the body frame.

    .venv/bin/python scripts/partition_oracle.py --seeds 0-4 --page docs/explanation/scaling.md \
        --section partition_oracle
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/: the view oracle's conditions
from onboard_view_oracle import CONDITIONS

from relloc.cli import argtypes
from relloc.engine import Engine
from relloc.evaluation.pages import check_page_args, print_table
from relloc.events import Event, measured_by
from relloc.methods import build_pipeline
from relloc.simulator.runner import Simulation
from relloc.simulator.scenarios import grid_scenario

KINDS = ("particle", "range_graph")
"""The filter kinds compared: the sampled filter and the deterministic range graph."""
SEED_STEP = 100
"""How far apart the filter seeds of ``two seeds`` are (the simulation stays the same)."""
Views = dict[float, dict[str, tuple[float, ...]]]
"""A run's estimates: stamp (rounded to the millisecond) -> robot -> position."""


def views(
    sim: Simulation, viewer: str, kind: str, seed: int, drop: Callable[[Event], bool] | None = None
) -> Views:
    """``viewer``'s filter of kind ``kind`` on the simulation's events, less those ``drop``
    says."""
    config = sim.config.with_modes(reference=viewer)
    config = replace(config, filter=replace(config.filter, kind=kind))
    pipeline = build_pipeline("pf", config, seed=seed)
    Engine([pipeline]).run(ev for ev in sim.events() if drop is None or not drop(ev))
    return {round(e.t, 3): e.positions for e in pipeline.estimates}


def distances(a: Views, b: Views, skip: set[str], lo: float, hi: float) -> list[float]:
    """Per common stamp in ``[lo, hi]`` and robot not in ``skip``: how far ``a`` is from ``b``."""
    out = []
    for t, pos in a.items():
        other = b.get(t)
        if other is None or not lo <= t <= hi:
            continue
        out += [math.dist(p, other[r]) for r, p in pos.items() if r not in skip and r in other]
    return out


def back_after(a: Views, b: Views, end: float, tol: float) -> float | None:
    """Seconds after ``end`` from which every view of ``a`` stays within ``tol`` m of ``b``'s
    at the same stamps (``None``: some view is still out at the last common stamp)."""
    stamps = sorted(t for t in a if t in b and t >= end)
    last_out = None
    for t in stamps:
        if max((math.dist(p, b[t][r]) for r, p in a[t].items() if r in b[t]), default=0.0) > tol:
            last_out = t
    if not stamps or last_out == stamps[-1]:
        return None
    return 0.0 if last_out is None else last_out - end


def one_seed(
    seed: int, kind: str, condition: str, args: argparse.Namespace
) -> tuple[list[float], list[float], float | None]:
    """The shifts, the two-seed spreads and the cut robot's ``back after`` of one simulation."""
    odometry, uwb = CONDITIONS[condition]
    sim = grid_scenario(
        seed, robots=args.robots, duration=args.duration, odometry=odometry, uwb=uwb
    )
    cut, lo, hi = args.robot, args.start, args.end

    def its_own(ev: Event) -> bool:
        return lo <= ev.t < hi and measured_by(ev, cut)

    def the_others(ev: Event) -> bool:
        return lo <= ev.t < hi and not measured_by(ev, cut)

    shift: list[float] = []
    spread: list[float] = []
    for viewer in sim.robots:
        if viewer == cut:
            continue
        whole = views(sim, viewer, kind, seed)
        shift += distances(views(sim, viewer, kind, seed, its_own), whole, {viewer, cut}, lo, hi)
        spread += distances(views(sim, viewer, kind, seed + SEED_STEP), whole, {viewer}, lo, hi)
    alone = views(sim, cut, kind, seed, the_others)
    return shift, spread, back_after(alone, views(sim, cut, kind, seed), hi, args.tol)


def row(kind: str, condition: str, args: argparse.Namespace) -> str:
    """One table row: a filter kind under one condition, over the seeds."""
    shift: list[float] = []
    spread: list[float] = []
    back: list[float | None] = []
    for seed in args.seeds:
        s, p, b = one_seed(seed, kind, condition, args)
        shift, spread, back = shift + s, spread + p, [*back, b]
    return (
        f"| {kind} | {condition} | {_max_median(shift)} | {_max_median(spread)} | "
        f"{_seconds(back)} |"
    )


def _max_median(values: list[float]) -> str:
    return f"{max(values):.3f} ({float(np.median(values)):.3f})" if values else "-"


def _seconds(values: list[float | None]) -> str:
    """Median and range of ``back after`` over the seeds (``never`` counts as the longest)."""
    keyed = sorted(math.inf if v is None else v for v in values)
    label = ["never" if math.isinf(v) else f"{v:.1f} s" for v in keyed]
    median = label[keyed.index(statistics.median_low(keyed))]
    return median if label[0] == label[-1] else f"{median} ({label[0]} to {label[-1]})"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--seeds", type=argtypes.seeds, default="0-4")
    p.add_argument("--robots", type=int, default=6)
    p.add_argument("--duration", type=float, default=60.0)
    p.add_argument("--robot", default="r1", help="the robot cut off")
    p.add_argument("--start", type=float, default=20.0)
    p.add_argument("--end", type=float, default=40.0)
    p.add_argument("--tol", type=float, default=0.02, help="how close counts as back (m)")
    p.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    p.add_argument("--conditions", nargs="+", default=["simulated", "exact heading, clean UWB"])
    p.add_argument("--page", type=Path, default=None)
    p.add_argument("--section", default=None)
    args = p.parse_args(argv)
    check_page_args(args.page, args.section)
    if unknown := set(args.conditions) - set(CONDITIONS):
        raise SystemExit(f"unknown conditions {sorted(unknown)}; choose from {list(CONDITIONS)}")
    seeds = ", ".join(str(s) for s in args.seeds)
    lines = [
        f"`grid`, {args.robots} robots, {args.duration:g} s, seeds {seeds}; `{args.robot}` cut off "
        f"from {args.start:g} to {args.end:g} s, offline in header order; distances in m, max "
        f"(median); back within {args.tol:g} m; `scripts/partition_oracle.py`",
        "",
        "| filter | errors simulated | shift of the others' views of each other | two seeds, "
        "no cut | cut robot back after |",
        "|---|---|---:|---:|---:|",
    ]
    for kind in args.kinds:
        for condition in args.conditions:
            lines.append(row(kind, condition, args))
            print(lines[-1], flush=True)
    print_table(lines, args.page, args.section)


if __name__ == "__main__":
    main()
