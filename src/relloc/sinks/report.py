"""Figures of a run: per method and robot APE statistics, ATE, convergence, as tables and JSON.

``evaluate`` turns the estimates an :class:`~relloc.engine.Engine` collected into a
:class:`ScenarioReport`. Estimates from the warm-up window are excluded from the APE figures
(the filter is still converging from its uniform prior then) and the convergence time is
reported separately. Multilateration is reported twice: ``multilateration`` with one
rotation/reflection fitted over the whole run (fair), and ``multilateration_oracle`` aligned to
ground truth at every step (an oracle, for reference only).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from typing import Any

from rich.console import Console
from rich.table import Table

from relloc.engine import Engine
from relloc.sinks.metrics import ApeStats, Paired, after, align, associate, ate, convergence_time


@dataclass
class MethodReport:
    robots: dict[str, ApeStats]
    ate: dict[str, float]
    convergence_s: float
    paired: dict[str, Paired] = field(repr=False)
    stats: dict[str, int] = field(default_factory=dict)
    compute_s: float = 0.0
    n_estimates: int = 0

    @property
    def mean_ape_median(self) -> float:
        vals = [s.median for s in self.robots.values() if s.n]
        return float(sum(vals) / len(vals)) if vals else math.nan

    def to_json(self) -> dict[str, Any]:
        return {
            "robots": {
                r: {
                    "ape_median": _num(s.median),
                    "ape_rmse": _num(s.rmse),
                    "ape_mean": _num(s.mean),
                    "ape_std": _num(s.std),
                    "ape_max": _num(s.max),
                    "ate_rmse": _num(self.ate.get(r, math.nan)),
                    "n": s.n,
                }
                for r, s in self.robots.items()
            },
            "mean_ape_median": _num(self.mean_ape_median),
            "convergence_s": _num(self.convergence_s),
            "n_estimates": self.n_estimates,
            "compute_s": round(self.compute_s, 4),
            "stats": dict(self.stats),
        }


@dataclass
class ScenarioReport:
    name: str
    warmup: float
    duration: float
    methods: dict[str, MethodReport]
    t0: float = 0.0
    """Time of the run's first event; the warm-up window is ``[t0, t0 + warmup)``."""

    def to_json(self) -> dict[str, Any]:
        return {
            "warmup_s": self.warmup,
            "duration_s": round(self.duration, 3),
            "methods": {m: r.to_json() for m, r in self.methods.items()},
        }


def _num(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 5)


def evaluate(engine: Engine, name: str, warmup: float, robots: list[str] | None = None) -> ScenarioReport:
    """APE/ATE/convergence of every pipeline of ``engine`` after ``warmup`` seconds."""
    t0 = engine.t_first or 0.0
    duration = (engine.t_last or t0) - t0
    methods: dict[str, MethodReport] = {}
    for p in engine.pipelines:
        names = robots or list(p.localizer.layout.others)
        paired = associate(p.estimates, engine.ground_truth, names)
        variants = [(p.name, "none")]
        if p.name.startswith("multilateration"):
            variants = [(p.name, "run"), (p.name + "_oracle", "step")]
        for method, mode in variants:
            aligned = align(paired, mode)
            conv = convergence_time(aligned)
            late = {r: after(q, t0 + warmup) for r, q in aligned.items()}
            methods[method] = MethodReport(
                robots={r: ApeStats.of(q.errors) for r, q in late.items()},
                ate={r: ate(q) for r, q in late.items()},
                convergence_s=conv,
                paired=aligned,
                stats=p.stats(),
                compute_s=p.compute_s,
                n_estimates=len(p.estimates),
            )
    return ScenarioReport(name, warmup, duration, methods, t0)


def make_console() -> Console:
    """A console for tables: the terminal's width, or 120 columns when output is redirected."""
    return Console() if sys.stdout.isatty() else Console(width=120)


def print_table(report: ScenarioReport, console: Console | None = None) -> None:
    """One row per method and robot: APE median / RMSE / max (m), n, and convergence time."""
    console = console or make_console()
    table = Table(title=f"{report.name}: APE after {report.warmup:g} s warm-up ({report.duration:.1f} s run)")
    for col in ("method", "robot", "APE median", "APE rmse", "APE max", "ATE", "n", "converged after"):
        table.add_column(col, justify="left" if col in ("method", "robot") else "right")
    for method, m in report.methods.items():
        conv = "never" if not math.isfinite(m.convergence_s) else f"{m.convergence_s:.1f} s"
        for k, (robot, s) in enumerate(sorted(m.robots.items())):
            if s.n == 0:
                cells = ["no estimate", "", "", "", "0"]
            else:
                cells = [f"{s.median:.3f}", f"{s.rmse:.3f}", f"{s.max:.3f}", f"{m.ate.get(robot, math.nan):.3f}", str(s.n)]
            table.add_row(method if k == 0 else "", robot, *cells, conv if k == 0 else "", end_section=k == len(m.robots) - 1)
    console.print(table)
