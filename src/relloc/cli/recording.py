"""``relloc run``: recorded data (a rosbag2 folder, or an MRCLAM data set folder) through the engine.

``run_recording`` streams a bag through every requested method (the same engine as the demo
and the live server), evaluates against motion capture when the bag has it, prints the APE
table, writes plots, TUM trajectories (by default to ``out/<recording>/``) and a JSON with the
demo's schema (the scenario named after the bag's folder). No ground truth ever reaches a
localizer.

Everything that would make the run useless is checked before it starts, once the bag is open:
a warm-up as long as the recording, a robot whose ``uwb_node`` matches no range topic (a
warning), no range at all between the team's robots (an error: every method fuses ranges).
``relloc calibrate`` lives in :mod:`relloc.cli.calibrate`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

from relloc.cli.common import UserError, check_warmup
from relloc.cli.progress import run_with_progress
from relloc.cli.rejections import rejection_lines
from relloc.config import TeamConfig
from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.plots import plot_ape, plot_ape_over_time, plot_trajectories
from relloc.evaluation.report import ScenarioReport, evaluate, make_console, print_table
from relloc.faults import Faults, inject
from relloc.methods import build_pipeline
from relloc.sinks.tum import write_tum
from relloc.sources.ingest import match_range_topics
from relloc.sources.mrclam import MrclamSource, is_mrclam
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
    sightings: str = "both"
    """What of each teammate sighting the source passes on: ``both``, ``range``, ``bearing``."""
    faults: Faults = field(default_factory=Faults)
    """Faults injected into the recording's event stream (:mod:`relloc.faults`)."""


def run_recording(bag: Path, config: TeamConfig, opts: RunOptions, console: Console | None = None) -> ScenarioReport:
    """Run every method of ``opts`` over ``bag`` and report APE against motion capture."""
    console = console or make_console()
    config = config.with_modes(
        heading=opts.heading, bias=opts.bias, odom_scale=opts.odom_scale, reference=opts.reference
    )
    if opts.particles:
        config = config.with_filter(particles=opts.particles, selfcal_particles=opts.particles)
    mrclam = is_mrclam(bag)
    source: RosbagSource | MrclamSource = MrclamSource(bag, config, sightings=opts.sightings) if mrclam else RosbagSource(bag, config)
    name = recording_name(bag)
    oracle = source.initial_poses() if isinstance(source, MrclamSource) else None
    pipelines = [
        build_pipeline(m, config, seed=opts.seed, models=opts.models, oracle_start=oracle) for m in opts.methods
    ]
    check_warmup(opts.warmup, source.duration, name)
    warnings = source.warnings if isinstance(source, MrclamSource) else [*source.warnings, *range_warnings(source)]
    for warning in warnings:
        console.print(f"[yellow]warning:[/] {escape(warning)}", soft_wrap=True)
    gt = GroundTruth(config.reference)
    engine = Engine(pipelines, truth_sinks=[gt.add])
    run_with_progress(
        engine,
        inject(source, opts.faults),
        label=name,
        duration=source.duration,
        console=console,
        enabled=opts.progress,
        start=source.start_time,
    )
    online = config.filter.self_calibration.bias_mode == "online"
    bias_truth = _bag_bias_truth(bag, config) if online and not mrclam else None
    report = evaluate(engine, gt, name, opts.warmup, bias_truth=bias_truth, truth_name="motion capture")
    print_table(report, console)
    lines = rejection_lines("the source", source.stats.rejected)
    for p in engine.pipelines:
        lines += rejection_lines(p.name, p.localizer.rejected)
    for line in lines:
        console.print(line, soft_wrap=True, highlight=False, markup=False)
    if opts.out is not None:
        write_outputs(report, engine, opts.out)
        console.print(f"plots and TUM trajectories written to {opts.out}/")
    if opts.json_path is not None:
        payload: dict[str, Any] = {"seed": opts.seed, "scenarios": {name: report.to_json()}}
        payload["scenarios"][name]["source"] = source.stats.as_dict()
        payload["scenarios"][name]["faults"] = {p.name: p.localizer.fault_counters() for p in engine.pipelines}
        opts.json_path.parent.mkdir(parents=True, exist_ok=True)
        opts.json_path.write_text(json.dumps(payload, indent=2))
        console.print(f"figures written to {opts.json_path}")
    return report


def range_warnings(source: RosbagSource) -> list[str]:
    """Robots whose ``uwb_node`` matches no range topic of the bag (they get no range).

    With no range between any two of the team's robots, raises :class:`UserError`: every
    method fuses ranges (``pf_uv``/``pf_ulv`` add detections to them), so the run would only
    say "no estimate" everywhere."""
    template = source.config.uwb.range_topic
    found = match_range_topics(source.topics, template)
    ranged = {node for pair in found.values() for node in pair}
    robots = [r for r in source.config.robots if r.uwb_node]
    if len(robots) >= 2 and not found:
        nodes = ", ".join(f"{r.name}={r.uwb_node}" for r in robots)
        raise UserError(
            f"no UWB range topic of the bag joins two of the team's nodes ({nodes}; template "
            f"{template!r}): every method needs ranges; check uwb_node and uwb.range_topic"
        )
    return [
        f"{r.name}: uwb_node {r.uwb_node!r} matches no range topic of the bag (template "
        f"{template!r}): it gets no range, so only its odometry moves it from the uniform prior"
        for r in robots
        if found and r.uwb_node not in ranged
    ]


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
