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

import numpy as np
from numpy.typing import NDArray
from rich.console import Console
from rich.table import Table

from relloc.engine import Engine
from relloc.evaluation.metrics import (
    CONVERGENCE_HOLD_S,
    CONVERGENCE_MIN_REST,
    CONVERGENCE_THRESHOLD_M,
    CONVERGENCE_TOLERANCE,
    ApeStats,
    Consistency,
    GroundTruth,
    HeadingPaired,
    Paired,
    after,
    align,
    associate,
    associate_headings,
    associate_shapes,
    ate,
    bias_errors,
    body_frame_paired,
    consistency,
    convergence_time,
    odometry_frame_rotation,
)

FloatArray = NDArray[np.float64]


@dataclass
class MethodReport:
    robots: dict[str, ApeStats]
    ate: dict[str, float]
    convergence_s: float
    paired: dict[str, Paired] = field(repr=False)
    stats: dict[str, int] = field(default_factory=dict)
    compute_s: float = 0.0
    n_estimates: int = 0
    headings: dict[str, HeadingPaired] = field(default_factory=dict, repr=False)
    """Heading-estimate mode: published relative headings against the truth, after the warm-up."""
    bias_errors: dict[str, FloatArray] = field(default_factory=dict, repr=False)
    """Online bias: ``|estimate - truth|`` per node pair after the warm-up (where a truth is known)."""
    final_biases: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Online bias: the last published (mean, std) per node pair."""
    bias_truth: dict[str, float] = field(default_factory=dict)
    final_scales: dict[str, tuple[float, float]] = field(default_factory=dict)
    body_frame: dict[str, ApeStats] = field(default_factory=dict)
    """APE in the reference robot's body frame after the warm-up
    (:func:`relloc.evaluation.metrics.body_frame_paired`); empty where the method has no
    heading of the reference (multilateration)."""
    frame_rotation_deg: float | None = None
    """Heading-estimate mode: rotation of the reference's odometry frame in the mocap frame (its
    mocap yaw minus odometry yaw at its first odometry message), by which the ground truth is
    turned for evaluation (evaluation only)."""
    consistency: dict[str, Consistency] = field(default_factory=dict, repr=False)
    """Per robot, the NEES of every estimate after the warm-up (methods with covariances)."""
    shape_robots: dict[str, ApeStats] = field(default_factory=dict)
    """Where the orientation was unobservable after the warm-up: the APE of those estimates'
    published shapes after one rotation/reflection fitted for them all (multilateration's
    treatment)."""
    unobservable_fraction: float = math.nan
    """Fraction of the estimates after the warm-up with ``orientation_observable`` False."""
    final_shape: dict[str, Any] = field(default_factory=dict)
    """The last estimate's shape in its gauge, pairwise distances, flag and status (methods
    that report a shape)."""
    observable_from_s: float = math.nan
    """Seconds from the start of the run to the estimate from which the orientation stays
    observable to the end (nan: never; 0 for methods that do not report it)."""
    particles: dict[str, Any] = field(default_factory=dict)
    """The particle count over time (methods that report one, :func:`particle_counts`)."""
    unseen: dict[str, list[list[float]]] = field(default_factory=dict)
    """Per robot, when the estimates listed it as unseen (:func:`unseen_intervals`)."""

    @property
    def mean_ape_median(self) -> float:
        vals = [s.median for s in self.robots.values() if s.n]
        return float(sum(vals) / len(vals)) if vals else math.nan

    def heading_median_deg(self, robot: str) -> float:
        h = self.headings.get(robot)
        return math.degrees(float(np.median(h.errors))) if h is not None and len(h.t) else math.nan

    def heading_spread_deg(self, robot: str) -> float:
        """Median published heading spread (circular std) after the warm-up (deg)."""
        h = self.headings.get(robot)
        return math.degrees(float(np.median(h.spread))) if h is not None and len(h.t) else math.nan

    def bias_error_median(self, pair: str) -> float:
        e = self.bias_errors.get(pair)
        return float(np.median(e)) if e is not None and e.size else math.nan

    def to_json(self) -> dict[str, Any]:
        robots: dict[str, dict[str, Any]] = {
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
        }
        for r, b in self.body_frame.items():
            entry = robots.setdefault(r, {})
            entry["body_ape_median"] = _num(b.median)
            entry["body_ape_rmse"] = _num(b.rmse)
        for r in self.headings:
            entry = robots.setdefault(r, {})
            entry["heading_median_deg"] = _num(self.heading_median_deg(r))
            entry["heading_spread_deg"] = _num(self.heading_spread_deg(r))
        for r, c in self.consistency.items():
            entry = robots.setdefault(r, {})
            entry["nees_median"] = _num(c.nees_median)
            entry["nees_mean"] = _num(c.nees_mean)
            entry["coverage95"] = _num(c.coverage)
        for r, s in self.shape_robots.items():
            entry = robots.setdefault(r, {})
            entry["shape_ape_median"] = _num(s.median)
            entry["shape_ape_rmse"] = _num(s.rmse)
            entry["shape_ape_max"] = _num(s.max)
        for r, (mean, std) in self.final_scales.items():
            entry = robots.setdefault(r, {})
            entry["odom_scale"] = _num(mean)
            entry["odom_scale_std"] = _num(std)
        out: dict[str, Any] = {
            "robots": robots,
            "mean_ape_median": _num(self.mean_ape_median),
            "convergence_s": _num(self.convergence_s),
            "n_estimates": self.n_estimates,
            "compute_s": round(self.compute_s, 4),
            "stats": dict(self.stats),
        }
        if self.final_biases:
            out["pairs"] = {
                pair: {
                    "bias": _num(mean),
                    "bias_std": _num(std),
                    "bias_true": _num(self.bias_truth.get(pair, math.nan)),
                    "bias_error_median": _num(self.bias_error_median(pair)),
                }
                for pair, (mean, std) in self.final_biases.items()
            }
        if self.final_shape:
            out["final_shape"] = self.final_shape
        if math.isfinite(self.unobservable_fraction):
            out["orientation_unobservable_fraction"] = _num(self.unobservable_fraction)
            out["orientation_observable_from_s"] = _num(self.observable_from_s)
        if self.frame_rotation_deg is not None:
            out["frame_rotation_deg"] = _num(self.frame_rotation_deg)
        if self.particles:
            out["particles"] = self.particles
        if self.unseen:
            out["unseen"] = self.unseen
        return out


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


def _num(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 5)


def evaluate(
    engine: Engine,
    truth: GroundTruth,
    name: str,
    warmup: float,
    robots: list[str] | None = None,
    bias_truth: dict[str, float] | None = None,
    truth_name: str = "ground truth",
) -> ScenarioReport:
    """APE/ATE/convergence of every pipeline of ``engine`` against ``truth`` after ``warmup`` s.

``truth`` is the :class:`GroundTruth` that was the engine's truth sink during the run.

    In heading-estimate mode the estimates are in the reference robot's odometry frame: the
    ground truth is turned into it by the reference's motion-capture yaw at its first odometry
    message (evaluation only), and the published relative headings are scored. Published
    online biases are scored against ``bias_truth`` (per node pair) where given.
    """
    t0 = engine.t_first or 0.0
    duration = (engine.t_last or t0) - t0
    methods: dict[str, MethodReport] = {}
    for p in engine.pipelines:
        names = robots or list(p.localizer.layout.others)
        loc = p.localizer
        rotation = 0.0
        frame_deg = None
        heading_pairs: dict[str, HeadingPaired] = {}
        if loc.config.filter.self_calibration.heading_mode == "estimate":
            ref = loc.layout.reference
            first = loc.first_odometry.get(ref)
            found = None if first is None else odometry_frame_rotation(truth, ref, first)
            if found is not None:
                rotation, frame_deg = found, math.degrees(found)
                yaws = getattr(loc, "odometry_yaws", {})
                heading_pairs = associate_headings(p.estimates, truth, yaws, rotation)
        paired = associate(p.estimates, truth, names, rotation)
        ref_yaws = getattr(loc, "odometry_yaws", {}).get(loc.layout.reference)
        body = {}
        if ref_yaws:
            body_pairs = body_frame_paired(p.estimates, truth, names, ref_yaws)
            body = {r: ApeStats.of(after(q, t0 + warmup).errors) for r, q in body_pairs.items()}
        last = p.estimates[-1] if p.estimates else None
        calibration: dict[str, Any] = {
            "headings": {
                r: _after_heading(h, t0 + warmup) for r, h in heading_pairs.items()
            },
            "bias_errors": bias_errors(p.estimates, bias_truth or {}, t0 + warmup),
            "final_biases": dict(last.biases) if last is not None else {},
            "bias_truth": {k: v for k, v in (bias_truth or {}).items() if last is not None and k in last.biases},
            "final_scales": dict(last.scales) if last is not None else {},
            "frame_rotation_deg": frame_deg,
        }
        honest = _honesty(p.estimates, truth, names, t0, warmup, rotation)
        variants = [(p.name, "none")]
        if p.name.startswith("multilateration"):
            variants = [(p.name, "run"), (p.name + "_oracle", "step")]
        for method, mode in variants:
            aligned = align(paired, mode)
            conv = convergence_time(aligned, start=t0)
            late = {r: after(q, t0 + warmup) for r, q in aligned.items()}
            methods[method] = MethodReport(
                robots={r: ApeStats.of(q.errors) for r, q in late.items()},
                ate={r: ate(q) for r, q in late.items()},
                convergence_s=conv,
                paired=aligned,
                stats=p.stats(),
                compute_s=p.compute_s,
                n_estimates=len(p.estimates),
                body_frame=body if mode == "none" else {},
                particles=particle_counts(p.estimates, t0, warmup),
                unseen=unseen_intervals(p.estimates, t0),
                **calibration,
                **(honest if mode == "none" else {}),
            )
    return ScenarioReport(name, warmup, duration, methods, t0, truth.reference, truth_name)


def unseen_intervals(estimates: list[Any], t0: float) -> dict[str, list[list[float]]]:
    """Per robot, the ``[first, last]`` seconds from the run's start of each stretch of
    consecutive estimates that listed it in ``Estimate.unseen`` (nothing heard of it)."""
    out: dict[str, list[list[float]]] = {}
    open_: dict[str, list[float]] = {}
    for e in estimates:
        flagged = getattr(e, "unseen", None) or {}
        t = round(e.t - t0, 3)
        for robot in flagged:
            if robot in open_:
                open_[robot][1] = t
            else:
                open_[robot] = [t, t]
                out.setdefault(robot, []).append(open_[robot])
        for robot in [r for r in open_ if r not in flagged]:
            del open_[robot]
    return out


def particle_counts(estimates: list[Any], t0: float, warmup: float) -> dict[str, Any]:
    """The particle count over time of estimates that carry one: ``series``, the change points
    ``[seconds from the run's start, count]`` (the first estimate's count, then each change),
    and the ``max``, ``final`` and ``median_after_warmup`` counts; empty for methods without."""
    counted = [(e.t, e.particles) for e in estimates if getattr(e, "particles", None) is not None]
    if not counted:
        return {}
    series: list[list[float]] = []
    for t, n in counted:
        if not series or series[-1][1] != n:
            series.append([round(t - t0, 3), n])
    late = [n for t, n in counted if t >= t0 + warmup] or [counted[-1][1]]
    return {
        "series": series,
        "max": max(n for _, n in counted),
        "final": counted[-1][1],
        "median_after_warmup": float(np.median(late)),
    }


def _honesty(
    estimates: list[Any], truth: GroundTruth, names: list[str], t0: float, warmup: float, rotation: float
) -> dict[str, Any]:
    """Consistency (NEES, 95 % coverage) after the warm-up, the orientation flag's history, and
    where it was unobservable the shape APE after one alignment for the run."""
    late = [e for e in estimates if e.t >= t0 + warmup]
    out: dict[str, Any] = {"consistency": consistency(estimates, truth, names, t0 + warmup, rotation)}
    if estimates and estimates[-1].shape:
        last = estimates[-1]
        out["final_shape"] = {
            "t": last.t,
            "orientation_observable": last.orientation_observable,
            "mode_weight": _num(last.mode_weight),
            "n_modes": last.n_modes,
            "gauge": last.shape_gauge,
            "shape": {r: [_num(x), _num(y)] for r, (x, y) in last.shape.items()},
            "distances": {p: [_num(m), _num(s)] for p, (m, s) in last.distances.items()},
            "status": last.status,
        }
    if not late:
        return out
    flags = np.array([e.orientation_observable for e in estimates])
    out["unobservable_fraction"] = float(np.mean([not e.orientation_observable for e in late]))
    bad = np.flatnonzero(~flags)
    if bad.size == 0:
        out["observable_from_s"] = 0.0
    elif bad[-1] + 1 < len(estimates):
        out["observable_from_s"] = float(estimates[bad[-1] + 1].t - t0)
    if out["unobservable_fraction"] > 0.0:
        # Only where the orientation was unobservable: a moving formation's gauge turns with it.
        hidden = [e for e in late if not e.orientation_observable]
        shaped = align(associate_shapes(hidden, truth, names, rotation), "run")
        out["shape_robots"] = {r: ApeStats.of(after(q, t0 + warmup).errors) for r, q in shaped.items()}
    return out


def _after_heading(h: HeadingPaired, t_start: float) -> HeadingPaired:
    keep = h.t >= t_start
    return HeadingPaired(h.t[keep], h.mean[keep], h.spread[keep], h.truth[keep])


def make_console() -> Console:
    """A console for tables: the terminal's width, or 120 columns when output is redirected."""
    return Console() if sys.stdout.isatty() else Console(width=120)


CONVERGENCE_CAPTION = (
    "converged after: seconds from the start of the run to the first time from which the worst "
    f"robot's APE stays under {CONVERGENCE_THRESHOLD_M:g} m for {CONVERGENCE_HOLD_S:g} s and for "
    f"{100 * (1 - CONVERGENCE_TOLERANCE):g} % of the rest of the run (never: not before the last "
    f"{100 * CONVERGENCE_MIN_REST:g} % of the run)"
)


def print_table(report: ScenarioReport, console: Console | None = None) -> None:
    """One row per method and robot: APE median / RMSE / max (m), n, and convergence time; the
    caption names the reference robot and defines "converged after"."""
    console = console or make_console()
    title = f"{report.name}: APE after {report.warmup:g} s warm-up ({report.duration:.1f} s run)"
    if report.reference:
        title += f", positions relative to {report.reference}"
    table = Table(title=title, caption=CONVERGENCE_CAPTION, caption_justify="left")
    for col in ("method", "robot", "APE median", "APE rmse", "APE max", "ATE", "body APE median", "n", "converged after", "NEES", "95 % cov."):
        table.add_column(col, justify="left" if col in ("method", "robot") else "right")
    for method, m in report.methods.items():
        conv = "never" if not math.isfinite(m.convergence_s) else f"{m.convergence_s:.1f} s"
        for k, (robot, s) in enumerate(sorted(m.robots.items())):
            b = m.body_frame.get(robot)
            body = f"{b.median:.3f}" if b is not None and b.n else ""
            if s.n == 0:
                cells = ["no estimate", "", "", "", "", "0"]
            else:
                cells = [f"{s.median:.3f}", f"{s.rmse:.3f}", f"{s.max:.3f}", f"{m.ate.get(robot, math.nan):.3f}", body, str(s.n)]
            c = m.consistency.get(robot)
            honest = ["", ""] if c is None else [f"{c.nees_median:.2f}", f"{100 * c.coverage:.0f} %"]
            table.add_row(
                method if k == 0 else "", robot, *cells, conv if k == 0 else "", *honest,
                end_section=k == len(m.robots) - 1,
            )
    console.print(table)
    console.print(NEES_CAPTION)
    print_shape_table(report, console)
    print_calibration_table(report, console)


NEES_CAPTION = (
    "NEES: median normalised estimation error squared of the published covariance after the "
    "warm-up (2 when consistent); 95 % cov.: estimates whose 95 % ellipse holds the truth"
)


def print_shape_table(report: ScenarioReport, console: Console | None = None) -> None:
    """Methods whose orientation was unobservable after the warm-up: the share of such
    estimates and the shape APE (one rotation/reflection fitted for the run)."""
    console = console or make_console()
    for method, m in report.methods.items():
        if not m.shape_robots:
            continue
        table = Table(
            title=(
                f"{report.name} / {method}: formation orientation unobservable in "
                f"{100 * m.unobservable_fraction:.0f} % of the estimates after the warm-up; "
                "shape APE after one rotation/reflection for the run"
            )
        )
        for col in ("robot", "shape APE median", "rmse", "max", "n"):
            table.add_column(col, justify="left" if col == "robot" else "right")
        for robot, s in sorted(m.shape_robots.items()):
            table.add_row(robot, f"{s.median:.3f}", f"{s.rmse:.3f}", f"{s.max:.3f}", str(s.n))
        console.print(table)


UNOBSERVABLE_SPREAD_DEG = 45.0
"""A published heading spread above this says: not observable yet (the robot has not moved)."""


def print_calibration_table(report: ScenarioReport, console: Console | None = None) -> None:
    """Self-calibration figures, where a method estimated any: per robot the relative heading
    (final mean and spread, median error after the warm-up) and odometry scale, per node pair
    the online bias (final mean and std, truth, median error after the warm-up)."""
    console = console or make_console()
    for method, m in report.methods.items():
        if m.headings or m.final_scales:
            table = Table(title=f"{report.name} / {method}: headings (reference's odometry frame) and odometry scales")
            for col in ("robot", "heading", "spread", "heading error (median)", "scale"):
                table.add_column(col, justify="left" if col == "robot" else "right")
            robots = sorted(set(m.headings) | set(m.final_scales))
            for robot in robots:
                h = m.headings.get(robot)
                cells = ["", "", ""]
                if h is not None and len(h.t):
                    spread = math.degrees(float(h.spread[-1]))
                    note = " (unobservable)" if spread > UNOBSERVABLE_SPREAD_DEG else ""
                    cells = [
                        f"{math.degrees(float(h.mean[-1])):.1f} deg",
                        f"{spread:.1f} deg{note}",
                        f"{m.heading_median_deg(robot):.2f} deg",
                    ]
                scale = m.final_scales.get(robot)
                cells.append("" if scale is None or not math.isfinite(scale[0]) else f"{scale[0]:.3f} +- {scale[1]:.3f}")
                table.add_row(robot, *cells)
            console.print(table)
        if m.final_biases:
            table = Table(title=f"{report.name} / {method}: online range biases (m)")
            for col in ("pair", "bias", "std", "true", "error (median)"):
                table.add_column(col, justify="left" if col == "pair" else "right")
            for pair, (mean, std) in sorted(m.final_biases.items()):
                true = m.bias_truth.get(pair)
                table.add_row(
                    pair,
                    f"{mean:.3f}",
                    f"{std:.3f}",
                    "" if true is None else f"{true:.3f}",
                    "" if true is None else f"{m.bias_error_median(pair):.3f}",
                )
            console.print(table)
