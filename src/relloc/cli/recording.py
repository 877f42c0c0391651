"""``relloc run`` and ``relloc calibrate``: recorded rosbag2 data through the engine.

``run_recording`` streams a bag through every requested method (the same engine as the demo
and the live server), evaluates against motion capture when the bag has it, prints the APE
table, writes plots, TUM trajectories and a JSON with the demo's schema (the scenario named
after the bag's folder). No ground truth ever reaches a localizer.

``calibrate`` estimates what the config needs from a recording with motion capture (UWB
node-pair biases from a bag or the error CSV; heading offsets from the first motion-capture
pose) and writes it into the team config, saying which recording it came from.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from rich.console import Console

from relloc.cli.progress import run_with_progress
from relloc.config import PairCalibration, TeamConfig
from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.plots import plot_ape, plot_ape_over_time, plot_trajectories
from relloc.evaluation.report import ScenarioReport, evaluate, make_console, print_table
from relloc.methods import build_pipeline
from relloc.sinks.tum import write_tum
from relloc.sources.rosbag import RosbagSource, recording_name


@dataclass(frozen=True)
class RunOptions:
    methods: tuple[str, ...] = ("pf", "multilateration")
    seed: int = 0
    warmup: float = 5.0
    particles: int | None = None
    models: Path | None = None
    out: Path | None = None
    json_path: Path | None = None
    progress: bool = True
    heading: str | None = None
    """Self-calibration modes (``None``: the config's): ``compass|estimate``."""
    bias: str | None = None
    """``calibrated|online``."""
    odom_scale: str | None = None
    """``fixed|online``."""
    reference: str | None = None
    """Another reference robot than the config's."""


def run_recording(bag: Path, config: TeamConfig, opts: RunOptions, console: Console | None = None) -> ScenarioReport:
    """Run every method of ``opts`` over ``bag`` and report APE against motion capture."""
    console = console or make_console()
    config = config.with_modes(
        heading=opts.heading, bias=opts.bias, odom_scale=opts.odom_scale, reference=opts.reference
    )
    if opts.particles:
        config = config.with_filter(particles=opts.particles, selfcal_particles=opts.particles)
    source = RosbagSource(bag, config)
    name = recording_name(bag)
    pipelines = [build_pipeline(m, config, seed=opts.seed, models=opts.models) for m in opts.methods]
    gt = GroundTruth(config.reference)
    engine = Engine(pipelines, truth_sinks=[gt.add])
    run_with_progress(
        engine,
        source,
        label=name,
        duration=source.duration,
        console=console,
        enabled=opts.progress,
        start=source.start_time,
    )
    bias_truth = _bag_bias_truth(bag, config) if config.filter.self_calibration.bias_mode == "online" else None
    report = evaluate(engine, gt, name, opts.warmup, bias_truth=bias_truth)
    print_table(report, console)
    for warning in source.warnings:
        console.print(f"[yellow]warning:[/] {warning}")
    rejected = {k: v for k, v in source.stats.rejected.items() if v}
    if rejected:
        console.print(f"source rejected: {rejected}")
    for p in engine.pipelines:
        if p.localizer.rejected:
            console.print(f"{p.name} rejected: {p.localizer.rejected}")
    if opts.out is not None:
        write_outputs(report, engine, opts.out)
        console.print(f"plots and TUM trajectories written to {opts.out}/")
    if opts.json_path is not None:
        payload: dict[str, Any] = {"seed": opts.seed, "scenarios": {name: report.to_json()}}
        payload["scenarios"][name]["source"] = source.stats.as_dict()
        opts.json_path.parent.mkdir(parents=True, exist_ok=True)
        opts.json_path.write_text(json.dumps(payload, indent=2))
        console.print(f"figures written to {opts.json_path}")
    return report


def _bag_bias_truth(bag: Path, config: TeamConfig) -> dict[str, float] | None:
    """Each node pair's range bias measured against motion capture in ``bag`` itself, to score
    online bias estimates (evaluation only; the filter never sees it). None without mocap."""
    from relloc.evaluation import calibration

    try:
        pairs = calibration.pair_biases_from_bag(bag, config)
    except Exception:  # no mocap or no matched pair: nothing to score against
        return None
    return {k: v.bias for k, v in pairs.items()}


def write_outputs(report: ScenarioReport, engine: Engine, out: Path) -> None:
    """Plots of ``report`` and one TUM file per method and robot (estimates and ground truth)."""
    out.mkdir(parents=True, exist_ok=True)
    plot_trajectories(report, out / f"{report.name}_trajectories.png")
    plot_ape(report, out / f"{report.name}_ape.png")
    plot_ape_over_time(report, out / f"{report.name}_ape_time.png")
    for method, m in report.methods.items():
        for robot, p in m.paired.items():
            if len(p.t):
                write_tum(out / "tum" / f"{method}_{robot}.txt", p.t, p.est)
                if method == next(iter(report.methods)):
                    write_tum(out / "tum" / f"groundtruth_{robot}.txt", p.t, p.gt)


def calibrate(
    source: Path,
    config: TeamConfig,
    *,
    node_map: dict[int, str] | None = None,
    headings: bool = False,
    fit_scale: bool = False,
) -> tuple[TeamConfig, dict[str, Any]]:
    """A copy of ``config`` with UWB pair calibration (and optionally heading offsets) from
    ``source``: a rosbag2 recording with motion capture, or a CSV of UWB errors."""
    from relloc.evaluation import calibration

    summary: dict[str, Any] = {"source": str(source)}
    if source.suffix.lower() == ".csv":
        pairs = calibration.pair_biases_from_csv(source, node_map or {1: "n_7", 3: "n_3", 4: "n_4", 5: "n_5"}, fit_scale=fit_scale)
    else:
        pairs = calibration.pair_biases_from_bag(source, config, fit_scale=fit_scale)
    merged: dict[str, PairCalibration] = {**config.uwb.pairs, **pairs}
    config = replace(config, uwb=replace(config.uwb, pairs=merged))
    summary["pairs"] = {k: {"bias": v.bias, "scale": v.scale, "sigma": v.sigma} for k, v in pairs.items()}
    if headings:
        if source.suffix.lower() == ".csv":
            raise ValueError("heading offsets need a bag with odometry and motion capture, not a CSV")
        offsets = calibration.heading_offsets_from_bag(source, config)
        for robot, deg in offsets.items():
            config = config.with_robot(robot, heading_offset_deg=round(deg, 2))
        summary["heading_offset_deg"] = offsets
    return config, summary
