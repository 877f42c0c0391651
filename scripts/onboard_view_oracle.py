"""Where an onboard view's error comes from: the grid team seen from each robot, as simulated
and with error sources taken out of the simulator.

``relloc serve --robot R`` runs the team's filter with R as the reference and turns the estimate
into R's body frame by R's odometry yaw. This runs the same offline, in header order, on
``grid_scenario(seed, robots=N, duration=S)`` (the team ``benchmarks/onboard.py`` serves, with
its shared-heading config: every odometry frame starts aligned), once with each robot as the
viewer, and scores each teammate's body-frame APE median after the warm-up. Conditions, each a
change of the simulator's error models only (the filter and its config stay the same):

* ``simulated``: as the benchmark runs it;
* ``exact heading``: the odometry's gyro bias and yaw-rate noise 0, so that every odometry
  heading is the truth's (the speed noise and wheel scales stay);
* ``clean UWB``: no heading-dependent antenna term, no NLOS spikes (the white noise and the
  pair biases, which the config knows, stay);
* both.

Per condition: the worst view from each viewer (its median over the seeds), the worst over all
views and seeds, the share of the views at most ``--bound`` m, and the worst view over all
viewers and seeds once each estimate is turned about its viewer by the angle that fits its
teammates best (``after a turn``: what is left when the bearing of the formation is not
counted). ``--page FILE --section NAME`` writes the table between the page's markers.

    .venv/bin/python scripts/onboard_view_oracle.py --seeds 0-4 --robots 6 --duration 60
"""

from __future__ import annotations

import argparse
import statistics
from dataclasses import replace
from pathlib import Path

import numpy as np

from relloc.cli import argtypes
from relloc.engine import Engine
from relloc.evaluation.gauges import body_frame_paired
from relloc.evaluation.metrics import GroundTruth, Paired
from relloc.evaluation.pages import check_page_args, print_table
from relloc.evaluation.report import evaluate
from relloc.methods import build_pipeline
from relloc.simulator.error_models import OdometryErrorModel, UwbErrorModel
from relloc.simulator.scenarios import grid_scenario

WARMUP = 10.0
"""Seconds left out of the scores at the start (as ``relloc demo``)."""
EXACT_HEADING = replace(OdometryErrorModel(), gyro_bias_max=0.0, sigma_w=0.0)
CLEAN_UWB = replace(UwbErrorModel(), orientation_amplitude=0.0, nlos_probability=0.0)
CONDITIONS: dict[str, tuple[OdometryErrorModel, UwbErrorModel]] = {
    "simulated": (OdometryErrorModel(), UwbErrorModel()),
    "exact heading": (EXACT_HEADING, UwbErrorModel()),
    "clean UWB": (OdometryErrorModel(), CLEAN_UWB),
    "exact heading, clean UWB": (EXACT_HEADING, CLEAN_UWB),
}


def body_views(
    seed: int, robots: int, duration: float, models: tuple[OdometryErrorModel, UwbErrorModel]
) -> tuple[dict[str, dict[str, float]], float]:
    """``{viewer: {teammate: body-frame APE median (m)}}`` of ``pf`` on one grid run, and the
    worst view's APE median after each estimate's best turn about its viewer."""
    odometry, uwb = models
    sim = grid_scenario(seed, robots=robots, duration=duration, odometry=odometry, uwb=uwb)
    views: dict[str, dict[str, float]] = {}
    turned = 0.0
    for viewer in sim.robots:
        config = sim.config.with_modes(reference=viewer)
        truth = GroundTruth(viewer)
        pipeline = build_pipeline("pf", config, seed=seed)
        engine = Engine([pipeline], truth_sinks=[truth.add])
        engine.run(sim.events())
        run = evaluate(engine, truth, "grid", WARMUP).methods["pf"]
        views[viewer] = {r: s.median for r, s in run.body_frame.items()}
        yaws = pipeline.localizer.odometry_yaws[viewer]
        pairs = body_frame_paired(pipeline.estimates, truth, list(views[viewer]), yaws)
        turned = max(turned, max(best_turn_errors(pairs).values()))
    return views, turned


def best_turn_errors(pairs: dict[str, Paired]) -> dict[str, float]:
    """Per teammate, the APE median after the warm-up once every estimate is turned about the
    viewer by the angle that brings its teammates closest to the truth (least squares)."""
    robots = list(pairs)
    t = pairs[robots[0]].t
    keep = t >= t[0] + WARMUP
    est = np.stack([pairs[r].est[keep] for r in robots], axis=1)  # (K, robots, 2)
    gt = np.stack([pairs[r].gt[keep] for r in robots], axis=1)
    cross = np.sum(est[..., 0] * gt[..., 1] - est[..., 1] * gt[..., 0], axis=1)
    dot = np.sum(est[..., 0] * gt[..., 0] + est[..., 1] * gt[..., 1], axis=1)
    angle = np.arctan2(cross, dot)
    c, s = np.cos(angle), np.sin(angle)
    x = c[:, None] * est[..., 0] - s[:, None] * est[..., 1]
    y = s[:, None] * est[..., 0] + c[:, None] * est[..., 1]
    errors = np.hypot(x - gt[..., 0], y - gt[..., 1])
    return {r: float(np.median(errors[:, k])) for k, r in enumerate(robots)}


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--seeds", type=argtypes.seeds, default="0-4")
    p.add_argument("--robots", type=int, default=6)
    p.add_argument("--duration", type=float, default=60.0)
    p.add_argument("--bound", type=float, default=0.15, help="a view's APE median asked (m)")
    p.add_argument("--page", type=Path, default=None)
    p.add_argument("--section", default=None)
    args = p.parse_args()
    check_page_args(args.page, args.section)
    viewers = [f"r{k}" for k in range(args.robots)]
    seeds = ", ".join(str(s) for s in args.seeds)
    lines = [
        f"`grid`, {args.robots} robots, {args.duration:g} s, seeds {seeds}, `pf` with each robot "
        f"as the viewer, body frame, after {WARMUP:g} s; worst view from each viewer (median "
        "over the seeds); `scripts/onboard_view_oracle.py`",
        "",
        "| errors simulated | "
        + " | ".join(viewers)
        + f" | worst | views <= {args.bound:g} m | after a turn |",
        "|---|" + "---:|" * (len(viewers) + 3),
    ]
    for name, models in CONDITIONS.items():
        results = [body_views(s, args.robots, args.duration, models) for s in args.seeds]
        runs = [views for views, _ in results]
        worst = [statistics.median(max(run[v].values()) for run in runs) for v in viewers]
        every = [e for run in runs for view in run.values() for e in view.values()]
        share = sum(e <= args.bound for e in every) / len(every)
        turned = max(t for _, t in results)
        cells = [f"{w:.2f}" for w in worst] + [f"{max(every):.2f}", f"{100 * share:.0f} %"]
        cells.append(f"{turned:.2f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    print_table(lines, args.page, args.section)


if __name__ == "__main__":
    main()
