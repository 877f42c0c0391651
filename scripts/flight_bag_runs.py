"""Simulated flights written as MURP-layout recordings, drafted by ``relloc init``, run and scored.

A recording of a flying team is run as a user runs it: ``relloc init`` on the
bag (motion capture, LinkTrack frames, nothing else), then ``relloc run --bias online`` on the
draft. This does the same on ``drones_six`` flights (``relloc.simulator.flight_bag``), seed by
seed, so that every step between the bag and the figures is the one the recording takes (the
draft's node mapping, lever arms, range delay, pair biases and range noise included), and
prints per seed and robot the APE mean and median, the yaw error's and the 95 % coverage of
``pf`` and ``pf_smoothed``. ``--body-term A`` adds the simulator's heading-dependent range error
(``UwbErrorModel.orientation_amplitude``: a tag's signal through the drone's body) of about A m.

    .venv/bin/python scripts/flight_bag_runs.py --seeds 0-3 --duration 60
    .venv/bin/python scripts/flight_bag_runs.py --seeds 0 --duration 60 --body-term 0.05

Each seed's bag, draft and run report stay under ``--work`` and are reused (empty it after
changing the code). ``--page FILE --section NAME`` writes the table between the page's markers.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import tomllib
from pathlib import Path
from typing import Any

from relloc.cli import argtypes, main
from relloc.evaluation.pages import check_page_args, print_table
from relloc.simulator.flight import SIX_TAG_UWB, drones_six_scenario
from relloc.simulator.flight_bag import write_flight_bag

REPO = Path(__file__).resolve().parents[1]
LINKTRACK = REPO / "examples" / "uwb_drivers" / "linktrack_ros2"
WARMUP = 10.0
"""Seconds left out of the scores at the start (as the drones_six figures of the docs)."""


def _run(seed: int, duration: float, body: float, work: Path) -> tuple[dict[str, Any], str]:
    """One seed: the bag, its draft and the run; the run's methods and the draft's reference."""
    folder = work / f"{'body' if body else 'base'}_{seed}_{int(duration)}"
    folder.mkdir(parents=True, exist_ok=True)
    bag, draft, report = folder / "bag", folder / "draft.toml", folder / "run_plain.json"
    if not bag.exists():
        uwb = dataclasses.replace(SIX_TAG_UWB, orientation_amplitude=body)
        write_flight_bag(bag, drones_six_scenario(seed, duration=duration, uwb=uwb), LINKTRACK)
    if not draft.exists():
        with contextlib.redirect_stdout(io.StringIO()):
            if main(["init", str(bag), "--out", str(draft)]) != 0:
                raise SystemExit(f"relloc init could not draft {bag}")
    if not report.exists():
        args = ["run", str(bag), "--config", str(draft), "--bias", "online", "--methods", "pf"]
        args += ["--warmup", str(WARMUP), "--no-progress", "--json", str(report)]
        with contextlib.redirect_stdout(io.StringIO()):
            if main(args) != 0:
                raise SystemExit(f"relloc run failed on {bag}")
    scenario = next(iter(json.loads(report.read_text())["scenarios"].values()))
    return scenario["methods"], tomllib.loads(draft.read_text())["reference"]


def main_() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--seeds", type=argtypes.seeds, default="0-3")
    p.add_argument("--duration", type=float, default=60.0, help="seconds of flight")
    p.add_argument("--body-term", type=float, default=0.0, help="heading-dependent error (m)")
    p.add_argument("--work", type=Path, default=Path("out/flight_bags"))
    p.add_argument("--page", type=Path, default=None)
    p.add_argument("--section", default=None)
    args = p.parse_args()
    check_page_args(args.page, args.section)
    lines = [
        f"`drones_six`, {args.duration:g} s, heading term {args.body_term:g} m, written as a MURP "
        f"bag, `relloc init`, `relloc run --bias online`, after {WARMUP:g} s; "
        "`scripts/flight_bag_runs.py`",
        "",
        "| seed | reference | robot | `pf` mean / median | yaw mean / median | coverage "
        "| `pf_smoothed` mean / median | yaw mean / median | coverage |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for seed in args.seeds:
        methods, reference = _run(seed, args.duration, args.body_term, args.work)
        causal, smoothed = methods["pf"]["robots"], methods["pf_smoothed"]["robots"]
        for robot in sorted(r for r, v in causal.items() if "ape_median" in v):
            cells = []
            for row in (causal[robot], smoothed[robot]):
                cells += [
                    f"{row['ape_mean']:.2f} / {row['ape_median']:.2f} m",
                    f"{row['yaw_error_mean_deg']:.1f} / {row['yaw_error_median_deg']:.1f} deg",
                    f"{100 * row['coverage95']:.0f} %",
                ]
            lines.append(f"| {seed} | {reference} | {robot} | " + " | ".join(cells) + " |")
    print_table(lines, args.page, args.section)


if __name__ == "__main__":
    main_()
