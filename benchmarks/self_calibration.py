"""Self-calibration: particles needed and time per update, for 2 and 5 robots.

The self-calibrating filter (``relloc.estimators.gaussian_sum.filter``) carries a Kalman filter over
positions, headings, scales and biases in every particle, so its cost per particle grows with
the square of the state (5 robots, online biases: 28 columns) while the number of particles it
needs stays small. This script measures both, on the simulator:

Pass ``--bias calibrated`` to tell the filter the true pair biases (headings only), and
``--range-error white`` to leave out the pairs' time-correlated range-error states (the filter
before they were added: white range noise beside each online bias).

* ``two``: two robots that both move (``a`` drives 0.8 m squares, ``b`` 1 m circles), one
  range, heading of ``b`` estimated in ``a``'s odometry frame, the pair bias online, odometry
  frames rotated at random (45 s);
* ``single``: the paper's single-range scenario (``r0`` static, ``r1`` circling) with the moving
  ``r1`` as reference: ``r0``'s heading is unobservable (it never moves), its position is not;
* ``five``: the paper's multi scenario (static ``r0``, four robots on patterns), headings
  estimated with ``r1`` as reference, the 10 pair biases online, frames rotated at random
  (the acceptance run of ``relloc demo --heading estimate --bias online``).

For each particle count and seed it runs the scenario (60 s, resp. 45 s), times every filter
update (prediction to the batch time, all range updates, estimate, resampling) and reports the
median time per update, and the accuracy after a 20 s warm-up: worst per-robot APE median,
worst heading error median over the moving robots, worst and median pair-bias error median.

    .venv/bin/python benchmarks/self_calibration.py                # all teams, default counts
    .venv/bin/python benchmarks/self_calibration.py --team five --particles 500 1000 2000 --seeds 0 1 2
    .venv/bin/python benchmarks/self_calibration.py --json out/bench/self_calibration.json

Times are wall clock on whatever machine runs it (the figures in docs/explanation/self-calibration.md come
from a 2-core machine shared with other jobs; read them as orders of magnitude).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

import relloc.estimators.gaussian_sum.localizer
from relloc.config import TeamConfig
from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.methods import build_pipeline
from relloc.runs.demo import DemoOptions, scenario_setup
from relloc.simulator import RobotMotion, Simulation

TEAMS = {"two": "pair", "single": "single", "five": "multi"}
DEFAULT_PARTICLES = {
    "two": (100, 300, 1000),
    "single": (100, 300, 1000),
    "five": (250, 500, 1000, 2000),
}


def two_moving(seed: int, bias: str) -> tuple[Simulation, TeamConfig, dict[str, float] | None]:
    """Two robots, both moving, frames rotated at random; no heading offset in the config (and
    no bias with ``bias="online"``)."""
    rng = np.random.default_rng(seed)
    yaw_a, yaw_b = rng.uniform(-math.pi, math.pi, 2)
    square = ((4.0, 0.2, 0.0), (math.pi / 2 / 0.6, 0.0, 0.6)) * 12
    robots = [
        RobotMotion("a", "n_1", -1.5, 0.3, float(yaw_a), square),
        RobotMotion("b", "n_2", 1.2, -0.4, float(yaw_b), ((60.0, 0.22, 0.22),)),
    ]
    sim = Simulation(robots, reference="a", seed=seed, duration=45.0, name="pair")
    config = replace(
        sim.config, robots=tuple(replace(r, heading_offset_deg=0.0) for r in sim.config.robots)
    )
    if bias == "online":
        config = replace(config, uwb=replace(config.uwb, pairs={}))
    truth = dict(sim.true_biases) if bias == "online" else None
    return sim, config.with_modes(heading="estimate", bias=bias), truth


def run_one(
    team: str, particles: int, seed: int, warmup: float, bias: str = "online"
) -> dict[str, Any]:
    scenario = TEAMS[team]
    if team == "two":
        sim, config, truth = two_moving(seed, bias)
    else:
        opts = DemoOptions(seed=seed, heading="estimate", bias=bias)
        sim, config, truth = scenario_setup(scenario, opts)
    config = config.with_filter(
        selfcal_particles=particles, selfcal_init_particles=max(10000, particles)
    )
    pipeline = build_pipeline("pf", config, seed=seed)
    loc = pipeline.localizer
    times: list[float] = []

    def timed(t: float, seconds: float, out: Any) -> None:
        if loc.initialized and out is not None:
            times.append(seconds)

    loc.step_timer = timed
    gt = GroundTruth(config.reference)
    engine = Engine([pipeline], truth_sinks=[gt.add])
    engine.run(sim.events())
    report = evaluate(engine, gt, scenario, warmup, bias_truth=truth)
    pf = report.methods["pf"]
    # robots that move (not the reference, whose heading is the frame's): r0 never does
    moving = [r for r in pf.headings if r not in ("r0", config.reference)]
    biases = [pf.bias_error_median(p) for p in pf.final_biases]
    return {
        "team": team,
        "bias_mode": bias,
        "robots": len(config.robots),
        "state_columns": loc.filter.layout.width,
        "particles": particles,
        "seed": seed,
        "update_ms_median": 1e3 * float(np.median(times[1:])) if len(times) > 1 else math.nan,
        "update_ms_p90": 1e3 * float(np.percentile(times[1:], 90)) if len(times) > 1 else math.nan,
        "updates": len(times),
        "ape_median_worst": max(s.median for s in pf.robots.values()),
        "heading_median_deg_worst": max(
            (pf.heading_median_deg(r) for r in moving), default=math.nan
        ),
        "bias_error_median_worst": max(biases) if biases else math.nan,
        "bias_error_median_median": float(np.median(biases)) if biases else math.nan,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--team", choices=("two", "single", "five", "all"), default="all")
    parser.add_argument("--particles", type=int, nargs="*", default=None)
    parser.add_argument("--seeds", type=int, nargs="*", default=[0])
    parser.add_argument("--warmup", type=float, default=20.0)
    parser.add_argument(
        "--bias",
        choices=("online", "calibrated"),
        default="online",
        help="pair biases estimated or told",
    )
    parser.add_argument(
        "--range-error",
        choices=("colored", "white"),
        default="colored",
        help="online pairs: a time-correlated range-error state beside each bias (default), or white noise only",
    )
    parser.add_argument("--json", default=None, metavar="FILE")
    args = parser.parse_args(argv)
    if args.range_error == "white":  # not a config key: the layout the localizer builds
        relloc.estimators.gaussian_sum.localizer.CalibrationLayout = functools.partial(  # type: ignore[misc]
            relloc.estimators.gaussian_sum.localizer.CalibrationLayout, colored_bias=False
        )
    teams = ("two", "single", "five") if args.team == "all" else (args.team,)
    rows = []
    header = f"{'team':5} {'M':>5} {'seed':>4} {'ms/update':>9} {'p90':>6} {'APE worst':>9} {'hdg worst':>9} {'bias worst':>10} {'bias med':>8}"
    print(header)
    for team in teams:
        for m in args.particles or DEFAULT_PARTICLES[team]:
            for seed in args.seeds:
                r = run_one(team, m, seed, args.warmup, args.bias)
                rows.append(r)
                print(
                    f"{team:5} {m:5d} {seed:4d} {r['update_ms_median']:9.2f} {r['update_ms_p90']:6.1f} "
                    f"{r['ape_median_worst']:9.3f} {r['heading_median_deg_worst']:9.2f} "
                    f"{r['bias_error_median_worst']:10.3f} {r['bias_error_median_median']:8.3f}",
                    flush=True,
                )
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
