"""``relloc demo``: the simulated scenarios of the paper, every method, tables, plots and JSON.

Runs the ``multi`` scenario (five robots: triangle, X, circle, rectangle and a static
reference) and the ``single`` scenario (two robots, one range) through the same engine that
processes real recordings, and evaluates each method against the simulator's ground truth.
The ``nav`` scenario is the paper's closed-loop experiment: one robot drives a rectangle around
the static reference robot with the particle filter's estimate as its only position feedback
(:mod:`relloc.navigation.closed_loop`); it reports positioning APE and path-tracking error.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from relloc.engine import Engine
from relloc.methods import build_pipeline
from relloc.sinks.plots import plot_ape, plot_ape_over_time, plot_trajectories
from relloc.sinks.report import ScenarioReport, evaluate, make_console, print_table
from relloc.sources.simulator import Simulation, multi_scenario, single_scenario


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


SCENARIOS: dict[str, Callable[..., Simulation]] = {"multi": multi_scenario, "single": single_scenario}

DETECTION_METHODS: frozenset[str] = frozenset({"pf_uv", "pf_ulv"})
"""Methods that fuse cooperative detections: the simulator then also simulates objects and
cameras (otherwise it leaves them out, which keeps the other methods' runs as they were)."""


def run_scenario(name: str, opts: DemoOptions, console: Console) -> ScenarioReport:
    sim = SCENARIOS[name](opts.seed, detections=bool(DETECTION_METHODS & set(opts.methods)))
    config = sim.config
    if opts.particles:
        config = config.with_filter(particles=opts.particles)
    pipelines = [build_pipeline(m, config, seed=opts.seed) for m in opts.methods]
    engine = Engine(pipelines, config.reference)
    with Progress(
        TextColumn(f"[bold]{name}[/]"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f} s simulated"),
        TimeRemainingColumn(),
        console=console,
        disable=not opts.progress,
        transient=True,
    ) as bar:
        task = bar.add_task(name, total=sim.duration)
        t_start: list[float] = []

        def progress(t: float) -> None:
            if not t_start:
                t_start.append(t)
            bar.update(task, completed=t - t_start[0])

        engine.run(sim.events(), progress)
    return evaluate(engine, name, opts.warmup)


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
    results: dict[str, Any] = {"seed": opts.seed, "scenarios": {}}
    for name in opts.scenarios:
        if name == "nav":
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
