"""Figures of a run: per method the registered metrics' results, as tables and JSON.

``evaluate`` turns the estimates an :class:`~relloc.engine.Engine` collected into a
:class:`ScenarioReport`: for every method it computes each metric of
:data:`relloc.evaluation.metric.METRICS` (the shipped ones: :mod:`relloc.evaluation.scores`,
:mod:`relloc.evaluation.selfcal_scores`) on
a :class:`~relloc.evaluation.metric.MethodRun`, and :meth:`MethodReport.to_json` and
:func:`print_table` show whatever those results show. Estimates from the warm-up window are
excluded from the figures (the filter is still converging from its uniform prior then) and the
convergence time is reported separately. Multilateration is reported twice:
``multilateration`` with one rotation/reflection fitted over the whole run (fair), and
``multilateration_oracle`` aligned to ground truth at every step (an oracle, for reference
only).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
from rich.console import Console
from rich.table import Table

from relloc.engine import Engine
from relloc.estimate import BODY_FRAME, HEADING_FRAME, Estimate
from relloc.evaluation import (  # noqa: F401 (registers)
    aligned_scores,
    distance_scores,
    scores,
    selfcal_scores,
    yaw_scores,
)
from relloc.evaluation.consistency import Consistency
from relloc.evaluation.metric import METRICS, Column, MethodRun, MetricResult
from relloc.evaluation.metrics import (
    ApeStats,
    FloatArray,
    GroundTruth,
    Paired,
    align,
    associate,
)
from relloc.evaluation.selfcal_metrics import HeadingPaired, odometry_frame_rotation

R = TypeVar("R", bound=MetricResult)


@dataclass
class MethodReport:
    """One method's figures: each metric's result by the metric's name, and the run's costs.

    The properties read the shipped metrics' results by what they are (``robots``: the APE
    statistics, ...); a metric that did not run reads as empty."""

    results: dict[str, MetricResult]
    paired: dict[str, Paired] = field(repr=False)
    """Every estimate associated with the ground truth, aligned as the method is scored."""
    stats: dict[str, int] = field(default_factory=dict)
    compute_s: float = 0.0
    n_estimates: int = 0
    frame: str = HEADING_FRAME
    """The frame of the method's last estimate (:attr:`relloc.estimate.Estimate.frame`), in
    which it is scored."""
    published: dict[str, Paired] = field(default_factory=dict, repr=False)
    """What the method publishes at each scored time (:meth:`relloc.estimate.Estimate.published`:
    where the orientation is not observable, the formation in its gauge), as the TUM files
    hold it; an aligned method's (multilateration) as scored."""
    published_frames: tuple[str, ...] = ()
    """The ROS frame ids of what the method published, in order of first use."""
    published_yaws: dict[str, FloatArray] = field(default_factory=dict, repr=False)
    """Per robot, the yaw (rad) published at each time of :attr:`published` (NaN where none):
    of 3D estimates only (:func:`published_yaws`), what their TUM files' quaternions carry."""

    def result(self, kind: type[R]) -> R | None:
        """The result of type ``kind``, if a metric produced one."""
        return next((r for r in self.results.values() if isinstance(r, kind)), None)

    @property
    def robots(self) -> dict[str, ApeStats]:
        """Per robot, the APE statistics after the warm-up."""
        r = self.result(scores.ApeResult)
        return r.stats if r is not None else {}

    @property
    def mean_ape_median(self) -> float:
        r = self.result(scores.ApeResult)
        return r.mean_median if r is not None else math.nan

    @property
    def ate(self) -> dict[str, float]:
        r = self.result(scores.AteResult)
        return r.values if r is not None else {}

    @property
    def convergence_s(self) -> float:
        r = self.result(scores.ConvergenceResult)
        return r.seconds if r is not None else math.nan

    @property
    def body_frame(self) -> dict[str, ApeStats]:
        r = self.result(scores.BodyFrameResult)
        return r.stats if r is not None else {}

    @property
    def consistency(self) -> dict[str, Consistency]:
        r = self.result(scores.ConsistencyResult)
        return r.robots if r is not None else {}

    @property
    def shape_robots(self) -> dict[str, ApeStats]:
        r = self.result(scores.ShapeResult)
        return r.stats if r is not None else {}

    @property
    def shape_paired(self) -> dict[str, Paired]:
        """The shape APE's pairs: the published shapes after its one rotation/reflection."""
        r = self.result(scores.ShapeResult)
        return r.paired if r is not None else {}

    @property
    def unobservable_fraction(self) -> float:
        r = self.result(scores.ShapeResult)
        return r.unobservable_fraction if r is not None else math.nan

    @property
    def headings(self) -> dict[str, HeadingPaired]:
        r = self.result(selfcal_scores.HeadingsResult)
        return r.headings if r is not None else {}

    def heading_median_deg(self, robot: str) -> float:
        r = self.result(selfcal_scores.HeadingsResult)
        return r.median_deg(robot) if r is not None else math.nan

    def heading_spread_deg(self, robot: str) -> float:
        r = self.result(selfcal_scores.HeadingsResult)
        return r.spread_deg(robot) if r is not None else math.nan

    @property
    def frame_rotation_deg(self) -> float | None:
        r = self.result(selfcal_scores.HeadingsResult)
        return r.frame_rotation_deg if r is not None else None

    @property
    def final_biases(self) -> dict[str, tuple[float, float]]:
        r = self.result(selfcal_scores.BiasResult)
        return r.final if r is not None else {}

    def bias_error_median(self, pair: str) -> float:
        r = self.result(selfcal_scores.BiasResult)
        return r.error_median(pair) if r is not None else math.nan

    def to_json(self) -> dict[str, Any]:
        robots: dict[str, dict[str, Any]] = {}
        method: dict[str, Any] = {}
        for result in self.results.values():
            for robot, fields in result.robot_json().items():
                robots.setdefault(robot, {}).update(fields)
            method.update(result.method_json())
        return {
            "robots": robots,
            **method,
            "n_estimates": self.n_estimates,
            "frame": self.frame,
            "published_frames": list(self.published_frames),
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
    reference: str = ""
    """The reference robot: every position is relative to it."""
    truth_name: str = "ground truth"
    """What the estimates are scored against: the simulator's ground truth, or motion capture."""

    def to_json(self) -> dict[str, Any]:
        return {
            "reference": self.reference,
            "warmup_s": self.warmup,
            "duration_s": round(self.duration, 3),
            "methods": {m: r.to_json() for m, r in self.methods.items()},
        }


def evaluate(
    engine: Engine,
    truth: GroundTruth,
    name: str,
    warmup: float,
    robots: list[str] | None = None,
    bias_truth: dict[str, float] | None = None,
    truth_name: str = "ground truth",
) -> ScenarioReport:
    """Every registered metric of every pipeline of ``engine`` against ``truth`` after ``warmup`` s.

    ``truth`` is the :class:`GroundTruth` that was the engine's truth sink during the run.

    Each estimate is scored in its own frame (:func:`~relloc.evaluation.metrics.truth_in_frame`):
    in heading-estimate mode the reference's body frame (its motion-capture yaw then), while the
    published relative headings, which are in the reference's odometry frame, are scored against
    the truth turned by the reference's motion-capture yaw at its first odometry message.
    Published online biases are scored against ``bias_truth`` (per node pair) where given. A
    localizer that can smooth the whole run afterwards (``smoothed_estimates()``, the smoother)
    gets a second row, ``<method>_smoothed``, beside the causal one.
    """
    t0 = engine.t_first or 0.0
    duration = (engine.t_last or t0) - t0
    methods: dict[str, MethodReport] = {}
    for p in engine.pipelines:
        names = robots or list(p.localizer.layout.others)
        loc = p.localizer
        rotation = 0.0
        frame_deg = None
        if loc.config.filter.self_calibration.heading_mode == "estimate":
            ref = loc.layout.reference
            first = loc.first_odometry.get(ref)
            found = None if first is None else odometry_frame_rotation(truth, ref, first)
            if found is not None:
                rotation, frame_deg = found, math.degrees(found)
        variants = [(p.name, "none", p.estimates)]
        if p.name.startswith("multilateration"):
            variants = [(p.name, "run", p.estimates), (p.name + "_oracle", "step", p.estimates)]
        smoothed = getattr(loc, "smoothed_estimates", None)
        if callable(smoothed) and (trajectory := smoothed()):
            variants.append((p.name + "_smoothed", "none", trajectory))
        for method, mode, estimates in variants:
            paired = associate(estimates, truth, names, rotation)
            run = MethodRun(
                method, estimates, truth, names, t0, warmup, align(paired, mode), mode,
                reference=loc.layout.reference, rotation=rotation, frame_rotation_deg=frame_deg,
                odometry_yaws=getattr(loc, "odometry_yaws", {}), bias_truth=bias_truth or {},
            )  # fmt: skip
            methods[method] = MethodReport(
                {metric.name: metric().compute(run) for metric in METRICS},
                run.paired,
                stats=p.stats(),
                compute_s=p.compute_s,
                n_estimates=len(estimates),
                frame=estimates[-1].frame if estimates else HEADING_FRAME,
                published=run.published,
                published_frames=tuple(dict.fromkeys(e.frame_id for e in run.shown)),
                published_yaws=published_yaws(run.shown, run.published),
            )
    return ScenarioReport(name, warmup, duration, methods, t0, truth.reference, truth_name)


def published_yaws(
    shown: Sequence[Estimate], published: dict[str, Paired]
) -> dict[str, FloatArray]:
    """Per robot with any, the yaw of the 3D estimates among ``shown`` (:attr:`Estimate.yaws`,
    its mean) at each time of its ``published`` pairs, NaN where the estimate has none. A 2D
    estimate gives none: its TUM files stay positions only, as they always were."""
    by_time = {e.t: e for e in shown if e.dimension == 3 and e.yaws}
    out: dict[str, FloatArray] = {}
    if not by_time:
        return out
    for robot, q in published.items():
        found = (by_time.get(t) for t in q.t.tolist())
        yaws = [e.yaws.get(robot, (math.nan, 0.0))[0] if e else math.nan for e in found]
        if any(math.isfinite(y) for y in yaws):
            out[robot] = np.array(yaws, dtype=float)
    return out


def make_console() -> Console:
    """A console for tables: the terminal's width, or 120 columns when output is redirected."""
    return Console() if sys.stdout.isatty() else Console(width=120)


def print_table(report: ScenarioReport, console: Console | None = None) -> None:
    """One row per method and robot with every registered metric's columns (the captions name
    the reference robot and define them), then the metrics' own tables by group."""
    console = console or make_console()
    title = f"{report.name}: APE after {report.warmup:g} s warm-up ({report.duration:.1f} s run)"
    if report.reference:
        body = any(m.frame == BODY_FRAME for m in report.methods.values())
        title += f", positions relative to {report.reference}" + (
            " in its body frame" if body else ""
        )
    rows = {
        (method, robot): {k: v for r in m.results.values() for k, v in r.cells(robot).items()}
        for method, m in report.methods.items()
        for robot in m.robots
    }
    columns = sorted(
        (
            c
            for metric in METRICS
            for c in metric.columns
            if not c.optional or any(c.header in cells for cells in rows.values())
        ),
        key=lambda c: c.rank,
    )
    captions = [metric.caption for metric in METRICS if metric.caption]
    table = Table(title=title, caption=captions[0] if captions else None, caption_justify="left")
    for col in ("method", "robot", *(c.header for c in columns)):
        table.add_column(col, justify="left" if col in ("method", "robot") else "right")
    for method, m in report.methods.items():
        for k, robot in enumerate(sorted(m.robots)):
            cells = rows[(method, robot)]
            table.add_row(
                method if k == 0 else "", robot, *(_cell(c, cells, k) for c in columns),
                end_section=k == len(m.robots) - 1,
            )  # fmt: skip
    console.print(table)
    for caption in captions[1:]:
        console.print(caption)
    for group in sorted({metric.table_group for metric in METRICS}):
        for method, m in report.methods.items():
            for metric in METRICS:
                found = m.results.get(metric.name)
                if metric.table_group == group and found is not None:
                    for extra in found.tables(report.name, method):
                        console.print(extra)


def _cell(column: Column, cells: dict[str, str], row: int) -> str:
    return "" if column.per_method and row else cells.get(column.header, "")
