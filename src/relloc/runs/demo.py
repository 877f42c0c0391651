"""The demo (``relloc demo``): the simulated scenarios of the paper, every method, tables, plots and JSON.

Runs the ``multi`` scenario (five robots: triangle, X, circle, rectangle and a static
reference) and the ``single`` scenario (two robots, one range) through the same engine that
processes real recordings, and evaluates each method against the simulator's ground truth.
``static`` (the multi team parked) and ``static_then_move`` (parked for 20 s, then driving) show
the estimate reporting an unobservable formation orientation, and the shape it still knows.
``grid`` (``--robots N``) is the scaling scenario: N robots on a grid, each driving its own
circle, every pair ranging, a static reference.
The ``nav`` scenario is the paper's closed-loop experiment: one robot drives a rectangle around
the static reference robot with the particle filter's estimate as its only position feedback
(:mod:`relloc.navigation.closed_loop`); it reports positioning APE and path-tracking error.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn

from relloc.config import TeamConfig
from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.plots import plot_ape, plot_ape_over_time, plot_trajectories
from relloc.evaluation.report import ScenarioReport, evaluate, make_console, print_table
from relloc.faults import Faults, inject
from relloc.methods import DETECTION_METHODS, build_pipeline, filter_header
from relloc.runs.checks import check_warmup, check_writable, runnable
from relloc.runs.progress import run_with_progress
from relloc.simulator import Simulation
from relloc.simulator.scenarios import SCENARIOS


@dataclass(frozen=True)
class DemoOptions:
    seed: int = 0
    warmup: float = 10.0
    particles: int | None = None
    methods: tuple[str, ...] = ("pf", "multilateration")
    scenarios: tuple[str, ...] = ("multi", "single", "nav")
    out: Path | None = None
    json_path: Path | None = None
    progress: bool = True
    heading: str | None = None
    """Self-calibration modes (``None``: the scenario config's): ``compass|estimate``."""
    bias: str | None = None
    """``calibrated|online``: online biases are not told to the filter."""
    odom_scale: str | None = None
    """``fixed|online``."""
    faults: Faults = field(default_factory=Faults)
    """Faults injected into every scenario's event stream (:mod:`relloc.faults`)."""
    robots: int = 5
    """Team size of the ``grid`` scenario."""
    filter_kind: str | None = None
    """The filter the particle methods run (``None``: the scenario config's ``auto``)."""


def build_simulation(name: str, opts: DemoOptions, **kwargs: Any) -> Simulation:
    """The scenario ``name`` for ``opts`` (the grid with ``opts.robots`` robots)."""
    if name == "grid":
        kwargs["robots"] = opts.robots
    return SCENARIOS[name](opts.seed, **kwargs)


MOVING_REFERENCE: dict[str, str] = {"multi": "r1", "single": "r1", "grid": "r1"}
"""Reference robot of each scenario in heading-estimate mode. The estimates are expressed in
the reference's odometry frame, which only the reference's own motion ties to the ranges: a
static reference (the scenarios' default ``r0``) would leave the whole formation's bearing
unobservable, so a moving robot (``r1``: the triangle, the circle, on the grid its own circle) takes
its place."""


def scenario_setup(
    name: str, opts: DemoOptions
) -> tuple[Simulation, TeamConfig, dict[str, float] | None]:
    """The simulation, the team config the filter gets, and the true pair biases to score
    online bias estimates against (None when biases are not estimated).

    In heading-estimate mode every robot's odometry frame is rotated by a random angle
    (``heading_offsets="random"``) and the config carries no heading offset; with online
    biases the config carries no pair bias (the simulator draws them in 0.1-0.5 m).
    """
    estimate = opts.heading == "estimate"
    kwargs: dict[str, Any] = {"detections": bool(DETECTION_METHODS & set(opts.methods))}
    if estimate:
        kwargs["heading_offsets"] = "random"
    sim = build_simulation(name, opts, **kwargs)
    config = sim.config
    if estimate:
        config = replace(
            config, robots=tuple(replace(r, heading_offset_deg=0.0) for r in config.robots)
        )
    if opts.bias == "online":
        config = replace(config, uwb=replace(config.uwb, pairs={}))
    config = config.with_modes(
        heading=opts.heading,
        bias=opts.bias,
        odom_scale=opts.odom_scale,
        reference=MOVING_REFERENCE.get(name) if estimate else None,
    )
    if opts.particles:
        config = config.with_filter(particles=opts.particles, selfcal_particles=opts.particles)
    if opts.filter_kind:
        config = config.with_filter(kind=opts.filter_kind)
    truth = dict(sim.true_biases) if config.filter.self_calibration.bias_mode == "online" else None
    return sim, config, truth


def run_scenario(name: str, opts: DemoOptions, console: Console) -> ScenarioReport:
    sim, config, bias_truth = scenario_setup(name, opts)
    if opts.heading == "estimate":
        console.print(
            f"{name}: headings estimated; reference {config.reference} (a moving robot: the "
            "estimates are in its odometry frame, which a static reference would leave unobservable)"
        )
    methods = runnable(opts.methods, config, console, name)
    pipelines = [build_pipeline(m, config, seed=opts.seed) for m in methods]
    if (header := filter_header(methods, config)) is not None:
        console.print(f"{name}: {header}", soft_wrap=True, highlight=False, markup=False)
    gt = GroundTruth(config.reference)
    engine = Engine(pipelines, truth_sinks=[gt.add])
    run_with_progress(
        engine,
        inject(sim.events(), opts.faults),
        label=name,
        duration=sim.duration,
        console=console,
        enabled=opts.progress,
    )
    return evaluate(engine, gt, name, opts.warmup, bias_truth=bias_truth)


def run_nav(opts: DemoOptions, console: Console) -> dict[str, Any]:
    """The ``nav`` scenario: closed-loop navigation on the PF estimate; table, plot, JSON."""
    from relloc.navigation.closed_loop import print_nav_table, run_nav_scenario
    from relloc.navigation.plots import plot_navigation

    with Progress(
        TextColumn("[bold]nav[/]"),
        BarColumn(),
        TextColumn("{task.completed:.0f} s simulated"),
        console=console,
        disable=not opts.progress,
        transient=True,
    ) as bar:
        task = bar.add_task("nav", total=None)
        result = run_nav_scenario(
            opts.seed, opts.particles, progress=lambda t: bar.update(task, completed=t)
        )
    print_nav_table(result, console)
    if opts.out is not None:
        plot_navigation(result, opts.out / "nav_path.png")
    return {"navigation": result.summary()}


def run_demo(opts: DemoOptions, console: Console | None = None) -> dict[str, Any]:
    console = console or make_console()
    for name in opts.scenarios:  # before any scenario runs
        if name in SCENARIOS:
            check_warmup(opts.warmup, build_simulation(name, opts).duration, name)
    if opts.out is not None:
        check_writable(opts.out)
    results: dict[str, Any] = {"seed": opts.seed, "scenarios": {}}
    for name in opts.scenarios:
        if name == "nav":
            if opts.heading == "estimate" or opts.odom_scale == "online":
                console.print(
                    "nav: skipped (closed-loop navigation runs with the compass and fixed scales only)"
                )
                continue
            results["scenarios"]["nav"] = run_nav(opts, console)
            continue
        report = run_scenario(name, opts, console)
        print_table(report, console)
        results["scenarios"][name] = report.to_json()
        if opts.out is not None:
            opts.out.mkdir(parents=True, exist_ok=True)
            plot_trajectories(report, opts.out / f"{name}_trajectories.png")
            plot_ape(report, opts.out / f"{name}_ape.png")
            plot_ape_over_time(report, opts.out / f"{name}_ape_time.png")
    if opts.out is not None:
        console.print(f"plots written to {opts.out}/")
    if opts.json_path is not None:
        opts.json_path.parent.mkdir(parents=True, exist_ok=True)
        opts.json_path.write_text(json.dumps(results, indent=2))
        console.print(f"figures written to {opts.json_path}")
    return results
