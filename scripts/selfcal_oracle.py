"""Self-calibration in the simulator against oracles that know the calibration.

    .venv/bin/python scripts/selfcal_oracle.py --seeds 0-4

Per seed, the five-robot scenario of ``relloc demo --heading estimate --bias online --warmup 20
--scenarios multi`` (method ``pf``, reference ``r1``) three times, on the same simulated run:

* **self-calibrating**: as the demo runs it, the headings and the pair biases online;
* **oracle**: the same filter (the Gaussian sum, headings estimated in the reference's odometry
  frame, so the gyros' drift is still tracked online) told every quantity it calibrates: every
  robot's true heading offset as a prior of ``ORACLE_HEADING_SIGMA_DEG``, every pair's true
  bias as the prior of its online bias (``bias_prior_sigma``; online, so that the filter keeps
  its state for the heading-dependent range error), every robot's odometry divided by its true
  wheel scale (fixed scales). The acceptance compares with this one;
* **gyro oracle**: the oracle on the same run with the odometry's constant yaw-rate biases
  removed (the simulator's ``true_gyro_biases`` set to 0: the same noise draws). This filter
  does not calibrate gyro biases, it follows them as a random walk of each heading; the gap
  between the two oracles is what a gyro bias costs it.

The scores are body-frame APE medians after the warm-up: where the reference would see each
robot. A heading error ``e`` of the reference turns every teammate's body-frame position by
``e``, so it costs about ``e`` times the robot's distance; the table prints, per run, the
median absolute error of the reference's heading after the warm-up (its heading in its own
odometry frame: odometry yaw plus the filter's estimate of the frame's drift, against the
motion capture's), and what each robot's body-frame APE would be with the reference's true
heading (the formation as estimated in the reference's odometry frame, turned by the true
heading instead).

Every robot should be at most ``BOUND`` m or within ``MARGIN`` m of the oracle
(docs/explanation/self-calibration.md, "The floor"). ``--gyro-bias-sigma S`` runs all three
with every robot's heading drift rate as a state of prior std ``S`` rad/s (``[filter.
self_calibration] gyro_bias_sigma``; 0 without; default: the scenario's config).
"""

from __future__ import annotations

import argparse
import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from relloc.config import TeamConfig
from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.evaluation.selfcal_metrics import odometry_frame_rotation
from relloc.methods import build_pipeline
from relloc.runs.demo import DemoOptions, scenario_setup
from relloc.simulator import Simulation

SCENARIO = "multi"
WARMUP = 20.0
BOUND = 0.20
"""Body-frame APE median every robot should reach (m) ..."""
MARGIN = 0.02
"""... or come within this much of the oracle (m)."""
ORACLE_HEADING_SIGMA_DEG = 1.0
"""The oracle's prior on each true heading offset (deg): known, yet a Gaussian in ``u``."""


@dataclass(frozen=True)
class RunFigures:
    """One run's body-frame APE median per robot, the same with the reference's true heading,
    and the median absolute error of the reference's heading (deg) after the warm-up."""

    body: dict[str, float]
    true_heading: dict[str, float]
    reference_heading_deg: float

    @property
    def worst(self) -> tuple[str, float]:
        return max(self.body.items(), key=lambda kv: kv[1])


def demo_options(seed: int) -> DemoOptions:
    return DemoOptions(
        seed=seed,
        warmup=WARMUP,
        methods=("pf",),
        scenarios=(SCENARIO,),
        progress=False,
        heading="estimate",
        bias="online",
    )


def oracle_config(sim: Simulation, config: TeamConfig) -> TeamConfig:
    """``config`` (the self-calibrating run's) told the truth: the simulator's heading offsets
    as a tight prior, its pair biases as the online biases' prior, the inverse of its wheel
    scales as the odometry's (the simulated odometry reads the true scale times the motion)."""
    truth = {r.name: r for r in sim.config.robots}
    robots = tuple(
        replace(
            r,
            heading_offset_deg=truth[r.name].heading_offset_deg,
            odom_scale=1.0 / sim.true_odom_scales[r.name],
        )
        for r in config.robots
    )
    config = replace(
        config, robots=robots, uwb=replace(config.uwb, pairs=dict(sim.config.uwb.pairs))
    )
    return config.with_filter(heading_prior_sigma_deg=ORACLE_HEADING_SIGMA_DEG)


def _turn(v: tuple[float, float] | np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def run_figures(sim: Simulation, config: TeamConfig, seed: int) -> RunFigures:
    """Run ``pf`` on ``sim`` with ``config`` and score it after the warm-up."""
    gt = GroundTruth(config.reference)
    pipeline = build_pipeline("pf", config, seed=seed)
    loc: Any = pipeline.localizer
    ref = config.reference
    psi: dict[float, float] = {}  # t -> the reference's estimated yaw in its odometry frame
    body_of: Callable[..., Any] = loc._body

    def recording_body(t: float, fe: Any) -> Any:
        out = body_of(t, fe)
        if out is not None:
            psi[t] = loc.odometry.pose(ref, t)[2] + loc.filter.heading(ref)[0]
        return out

    loc._body = recording_body  # instrumented on this instance only
    engine = Engine([pipeline], truth_sinks=[gt.add])
    engine.run(sim.events())
    report = evaluate(engine, gt, SCENARIO, WARMUP)
    robots = report.to_json()["methods"]["pf"]["robots"]
    body = {r: float(v["body_ape_median"]) for r, v in robots.items() if "body_ape_median" in v}
    first = loc.first_odometry.get(ref)
    rotation = None if first is None else odometry_frame_rotation(gt, ref, first)
    errors: list[float] = []
    true_heading: dict[str, list[float]] = {r: [] for r in body}
    start = (engine.t_first or 0.0) + WARMUP
    for est in pipeline.estimates:
        pose = gt.pose_at(ref, est.t)
        if est.t < start or est.t not in psi or pose is None or rotation is None:
            continue
        e = math.remainder(psi[est.t] - (pose[2] - rotation), math.tau)
        errors.append(abs(e))
        for robot in body:
            truth = gt.relative_at(robot, est.t)
            if truth is None or robot not in est.positions:
                continue
            # body-frame estimate turned back by the heading error: the true heading's view
            corrected = _turn(est.positions[robot], e)
            true_body = _turn(truth, -pose[2])
            true_heading[robot].append(float(np.linalg.norm(corrected - true_body)))
    return RunFigures(
        body,
        {r: statistics.median(v) for r, v in true_heading.items() if v},
        math.degrees(statistics.median(errors)) if errors else math.nan,
    )


def setup(seed: int, gyro_bias_sigma: float | None) -> tuple[Simulation, TeamConfig]:
    """A fresh simulated run of the scenario and its config (``gyro_bias_sigma`` set if given)."""
    sim, config, _ = scenario_setup(SCENARIO, demo_options(seed))
    if gyro_bias_sigma is not None:
        config = config.with_filter(gyro_bias_sigma=gyro_bias_sigma)
    return sim, config


def seed_figures(
    seed: int, gyro_bias_sigma: float | None = None
) -> tuple[RunFigures, RunFigures, RunFigures]:
    """The self-calibrating run's, the oracle's and the gyro oracle's figures."""
    sim, config = setup(seed, gyro_bias_sigma)
    own = run_figures(sim, config, seed)
    sim, config = setup(seed, gyro_bias_sigma)  # a fresh event stream
    oracle = run_figures(sim, oracle_config(sim, config), seed)
    sim, config = setup(seed, gyro_bias_sigma)
    sim.true_gyro_biases = dict.fromkeys(sim.true_gyro_biases, 0.0)
    gyro = run_figures(sim, oracle_config(sim, config), seed)
    return own, oracle, gyro


def passes(own: float, oracle: float) -> bool:
    return own <= BOUND or own <= oracle + MARGIN


def parse_seeds(text: str) -> list[int]:
    if "-" in text:
        lo, hi = text.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(s) for s in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0-4", help="0-4 or 0,3 (default: 0-4)")
    parser.add_argument(
        "--gyro-bias-sigma",
        type=float,
        default=None,
        help="prior std of each robot's heading drift rate state, rad/s (0: none; "
        "default: the scenario's config)",
    )
    args = parser.parse_args(argv)
    print(
        "| seed | robot | self-calibrating (m) | oracle (m) | gyro oracle (m) | excess (m) "
        "| passes | self-calibrating, true reference heading (m) |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    failing = 0
    summary = []
    for seed in parse_seeds(args.seeds):
        own, oracle, gyro = seed_figures(seed, args.gyro_bias_sigma)
        for robot in sorted(own.body):
            o = oracle.body.get(robot, math.nan)
            ok = passes(own.body[robot], o)
            failing += not ok
            print(
                f"| {seed} | {robot} | {own.body[robot]:.3f} | {o:.3f} | "
                f"{gyro.body.get(robot, math.nan):.3f} | {own.body[robot] - o:+.3f} | "
                f"{'yes' if ok else 'NO'} | {own.true_heading.get(robot, math.nan):.3f} |"
            )
        summary.append((seed, own, oracle, gyro))
    print()
    print(
        "| seed | worst robot: self-calibrating (m) | oracle (m) | gyro oracle (m) "
        "| reference heading error, median (deg): self / oracle / gyro oracle |"
    )
    print("| --- | --- | --- | --- | --- |")
    for seed, own, oracle, gyro in summary:
        robot, value = own.worst
        print(
            f"| {seed} | {value:.3f} ({robot}) | {oracle.worst[1]:.3f} ({oracle.worst[0]}) | "
            f"{gyro.worst[1]:.3f} ({gyro.worst[0]}) | {own.reference_heading_deg:.1f} / "
            f"{oracle.reference_heading_deg:.1f} / {gyro.reference_heading_deg:.1f} |"
        )
    print(f"robots failing (over {BOUND} m and over the oracle + {MARGIN} m): {failing}")
    return 1 if failing else 0


if __name__ == "__main__":
    raise SystemExit(main())
