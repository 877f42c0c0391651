"""A run (``relloc run``): a source (a rosbag2 recording, an MRCLAM data set, a simulated scenario) through the engine.

``run_recording`` streams the source the path names (:mod:`relloc.sources.table`) through every
requested method (the same engine as the demo and the live server), evaluates against its
motion capture (or the simulator's ground truth), prints the APE table, writes plots, TUM
trajectories (by default to ``out/<recording>/``), an MCAP file of ROS 2 messages (``--mcap``,
:mod:`relloc.sinks.mcap`) and a JSON with the demo's schema (the scenario named after the
recording). No ground truth ever reaches a localizer.

Everything that would make the run useless is checked before it starts, once the source is
open: a warm-up as long as the recording, and for a bag a robot whose ``uwb_node`` matches no
range topic (a warning) or no range at all between the team's robots (an error: every method
fuses ranges, :meth:`~relloc.sources.rosbag.RosbagSource.check_ranges`).
The command (:mod:`relloc.cli`) only parses its arguments into :class:`RunOptions` and calls
:func:`run_recording`; ``relloc calibrate``'s library part is :mod:`relloc.drafting.calibrate`.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

from relloc.config import TeamConfig
from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.plots import plot_ape, plot_ape_over_time, plot_trajectories
from relloc.evaluation.report import ScenarioReport, evaluate, make_console, print_table
from relloc.events import Event, RangeEvent
from relloc.faults import Faults, inject
from relloc.methods import DETECTION_METHODS, build_pipeline, filter_header
from relloc.runs.checks import check_warmup, runnable
from relloc.runs.progress import run_with_progress
from relloc.runs.rejections import rejection_lines
from relloc.sinks.mcap import write_mcap
from relloc.sinks.tum import write_tum
from relloc.sources.span import SpanSource
from relloc.sources.table import SourceOptions, source_kind


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
    filter_kind: str | None = None
    """The filter the particle methods run (``None``: the config's ``[filter] kind``)."""
    span: tuple[float, float] | None = None
    """Only the events between these seconds from the recording's start (:mod:`relloc.sources.span`)."""
    mcap: Path | None = None
    """An MCAP file of the run's estimates, flags, truth and ranges (:mod:`relloc.sinks.mcap`)."""


def run_recording(
    path: Path, config: TeamConfig | None, opts: RunOptions, console: Console | None = None
) -> ScenarioReport:
    """Run every method of ``opts`` over the source ``path`` names (:mod:`relloc.sources.table`)
    and report APE against its ground truth; ``config`` is ``None`` for a simulated scenario."""
    console = console or make_console()
    kind = source_kind(path)
    options = SourceOptions(
        seed=opts.seed,
        sightings=opts.sightings,
        detections=bool(DETECTION_METHODS & set(opts.methods)),
    )
    source = kind.open(path, None if config is None else _with_options(config, opts), options)
    if opts.span is not None:
        source = SpanSource(source, opts.span)
    config = source.config if config is not None else _with_options(source.config, opts)
    name = source.name
    oracle = source.initial_poses()
    methods = runnable(opts.methods, config, console, name)
    pipelines = [
        build_pipeline(m, config, seed=opts.seed, models=opts.models, oracle_start=oracle)
        for m in methods
    ]
    check_warmup(opts.warmup, source.duration, name)
    if (header := filter_header(methods, config)) is not None:
        console.print(f"{name}: {header}", soft_wrap=True, highlight=False, markup=False)
    for warning in source.warnings:
        console.print(f"[yellow]warning:[/] {escape(warning)}", soft_wrap=True)
    gt = GroundTruth(config.reference)
    engine = Engine(pipelines, truth_sinks=[gt.add])
    ranges: list[RangeEvent] = []
    events = inject(source, opts.faults)
    run_with_progress(
        engine,
        events if opts.mcap is None else _tap_ranges(events, ranges),
        label=name,
        duration=source.duration,
        console=console,
        enabled=opts.progress,
        start=source.start_time,
    )
    online = config.filter.self_calibration.bias_mode == "online"
    bias_truth = _bag_bias_truth(path, config) if online and kind.calibrates else None
    report = evaluate(
        engine, gt, name, opts.warmup, bias_truth=bias_truth, truth_name=kind.truth_name
    )
    print_table(report, console)
    lines = rejection_lines("the source", source.stats.rejected)
    for p in engine.pipelines:
        lines += rejection_lines(p.name, p.localizer.rejected)
    for line in lines:
        console.print(line, soft_wrap=True, highlight=False, markup=False)
    if opts.out is not None:
        write_outputs(report, engine, opts.out)
        console.print(f"plots and TUM trajectories written to {opts.out}/")
    if opts.mcap is not None:
        write_mcap(opts.mcap, engine, report, distro=config.ros_distro, ranges=ranges)
        console.print(f"MCAP written to {opts.mcap}")
    if opts.json_path is not None:
        payload: dict[str, Any] = {"seed": opts.seed, "scenarios": {name: report.to_json()}}
        payload["scenarios"][name]["source"] = source.stats.as_dict()
        payload["scenarios"][name]["faults"] = {
            p.name: p.localizer.fault_counters() for p in engine.pipelines
        }
        opts.json_path.parent.mkdir(parents=True, exist_ok=True)
        opts.json_path.write_text(json.dumps(payload, indent=2))
        console.print(f"figures written to {opts.json_path}")
    return report


def _tap_ranges(events: Iterable[Event], into: list[RangeEvent]) -> Iterator[Event]:
    """``events``, each range also appended to ``into`` (what the MCAP file shows)."""
    for ev in events:
        if isinstance(ev, RangeEvent):
            into.append(ev)
        yield ev


def _with_options(config: TeamConfig, opts: RunOptions) -> TeamConfig:
    """``config`` with the run's self-calibration modes, reference and particle count."""
    config = config.with_modes(
        heading=opts.heading, bias=opts.bias, odom_scale=opts.odom_scale, reference=opts.reference
    )
    if opts.particles:
        config = config.with_filter(particles=opts.particles, selfcal_particles=opts.particles)
    if opts.filter_kind:
        config = config.with_filter(kind=opts.filter_kind)
    return config


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
                shown = m.published.get(robot, p)
                write_tum(
                    out / "tum" / f"{method}_{robot}.txt",
                    shown.t,
                    shown.est,
                    m.published_frames,
                    yaws=m.published_yaws.get(robot),
                )
                if method == next(iter(report.methods)):
                    write_tum(out / "tum" / f"groundtruth_{robot}.txt", p.t, p.gt)
