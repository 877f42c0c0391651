"""The shipped metrics of positions and their uncertainty, one class each, in the order the
report shows them (the self-calibration ones: :mod:`relloc.evaluation.selfcal_scores`).

The definitions (APE, ATE, convergence, NEES, body frame, shapes) are those of
:mod:`relloc.evaluation.metrics`; each class here scores one method's run with one of them and
says how its figures appear in the JSON and the tables (:mod:`relloc.evaluation.metric`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rich.table import Table

from relloc.evaluation.consistency import Consistency, consistency
from relloc.evaluation.gauges import associate_shapes, body_frame_paired
from relloc.evaluation.metric import Column, MethodRun, Metric, MetricResult, num, register_metric
from relloc.evaluation.metrics import (
    CONVERGENCE_HOLD_S,
    CONVERGENCE_MIN_REST,
    CONVERGENCE_THRESHOLD_M,
    CONVERGENCE_TOLERANCE,
    ApeStats,
    Paired,
    after,
    align,
    ate,
    convergence_time,
)

FloatArray = NDArray[np.float64]


# ---------------------------------------------------------------------------- APE, ATE
@dataclass(frozen=True)
class ApeResult(MetricResult):
    stats: dict[str, ApeStats]
    """Per robot, the APE statistics after the warm-up."""

    @property
    def mean_median(self) -> float:
        vals = [s.median for s in self.stats.values() if s.n]
        return float(sum(vals) / len(vals)) if vals else math.nan

    def robot_json(self) -> dict[str, dict[str, Any]]:
        return {
            r: {
                "ape_median": num(s.median),
                "ape_rmse": num(s.rmse),
                "ape_mean": num(s.mean),
                "ape_std": num(s.std),
                "ape_max": num(s.max),
                "n": s.n,
            }
            for r, s in self.stats.items()
        }

    def method_json(self) -> dict[str, Any]:
        return {"mean_ape_median": num(self.mean_median)}

    def cells(self, robot: str) -> dict[str, str]:
        s = self.stats.get(robot)
        if s is None or s.n == 0:
            return {"APE median": "no estimate", "n": "0"}
        return {
            "APE median": f"{s.median:.3f}",
            "APE rmse": f"{s.rmse:.3f}",
            "APE max": f"{s.max:.3f}",
            "n": str(s.n),
        }


@register_metric
class Ape(Metric):
    """APE of each robot's relative position after the warm-up: median, mean, RMSE, std, max."""

    name = "ape"
    columns = (
        Column("APE median", 10),
        Column("APE rmse", 11),
        Column("APE max", 12),
        Column("n", 40),
    )

    def compute(self, run: MethodRun) -> ApeResult:
        return ApeResult({r: ApeStats.of(q.errors) for r, q in run.late.items()})


@dataclass(frozen=True)
class AteResult(MetricResult):
    values: dict[str, float]
    """Per robot, the ATE RMSE after the warm-up (m)."""
    counts: dict[str, int] = field(default_factory=dict)
    """Per robot, the estimates it was computed over."""

    def robot_json(self) -> dict[str, dict[str, Any]]:
        return {r: {"ate_rmse": num(v)} for r, v in self.values.items()}

    def cells(self, robot: str) -> dict[str, str]:
        if not self.counts.get(robot):
            return {}
        return {"ATE": f"{self.values.get(robot, math.nan):.3f}"}


@register_metric
class Ate(Metric):
    """ATE: the APE RMSE after one SE(2) alignment of each robot's relative trajectory."""

    name = "ate"
    columns = (Column("ATE", 20),)

    def compute(self, run: MethodRun) -> AteResult:
        return AteResult(
            {r: ate(q) for r, q in run.late.items()}, {r: len(q.t) for r, q in run.late.items()}
        )


# ---------------------------------------------------------------------------- convergence
CONVERGENCE_CAPTION = (
    "converged after: seconds from the start of the run to the first time from which the worst "
    f"robot's APE stays under {CONVERGENCE_THRESHOLD_M:g} m for {CONVERGENCE_HOLD_S:g} s and for "
    f"{100 * (1 - CONVERGENCE_TOLERANCE):g} % of the rest of the run (never: not before the last "
    f"{100 * CONVERGENCE_MIN_REST:g} % of the run)"
)


@dataclass(frozen=True)
class ConvergenceResult(MetricResult):
    seconds: float
    """From the start of the run (nan: never)."""

    def method_json(self) -> dict[str, Any]:
        return {"convergence_s": num(self.seconds)}

    def cells(self, robot: str) -> dict[str, str]:
        return {
            "converged after": "never"
            if not math.isfinite(self.seconds)
            else f"{self.seconds:.1f} s"
        }


@register_metric
class Convergence(Metric):
    """Convergence time (:func:`relloc.evaluation.metrics.convergence_time`)."""

    name = "convergence"
    columns = (Column("converged after", 50, per_method=True),)
    caption = CONVERGENCE_CAPTION

    def compute(self, run: MethodRun) -> ConvergenceResult:
        return ConvergenceResult(convergence_time(run.paired, start=run.t0))


# ---------------------------------------------------------------------------- body frame
@dataclass(frozen=True)
class BodyFrameResult(MetricResult):
    stats: dict[str, ApeStats]

    def robot_json(self) -> dict[str, dict[str, Any]]:
        return {
            r: {"body_ape_median": num(b.median), "body_ape_rmse": num(b.rmse)}
            for r, b in self.stats.items()
        }

    def cells(self, robot: str) -> dict[str, str]:
        b = self.stats.get(robot)
        return {"body APE median": f"{b.median:.3f}"} if b is not None and b.n else {}


@register_metric
class BodyFrameApe(Metric):
    """APE in the reference robot's body frame (:func:`~relloc.evaluation.gauges.body_frame_paired`):
    unaligned methods that track the reference's odometry yaw."""

    name = "body_frame"
    columns = (Column("body APE median", 30),)

    def compute(self, run: MethodRun) -> BodyFrameResult:
        ref_yaws = run.odometry_yaws.get(run.reference)
        if run.aligned or not ref_yaws:
            return BodyFrameResult({})
        pairs = body_frame_paired(run.estimates, run.truth, run.robots, ref_yaws)
        return BodyFrameResult(
            {r: ApeStats.of(after(q, run.start).errors) for r, q in pairs.items()}
        )


# ---------------------------------------------------------------------------- consistency
NEES_CAPTION = (
    "NEES: median normalised estimation error squared of the published covariance after the "
    "warm-up (its dimension when consistent: 2, 3 in 3D); 95 % cov.: estimates whose 95 % "
    "ellipse (ellipsoid in 3D) holds the truth"
)


@dataclass(frozen=True)
class ConsistencyResult(MetricResult):
    robots: dict[str, Consistency]
    """Per robot, the NEES of every estimate after the warm-up (methods with covariances)."""

    def robot_json(self) -> dict[str, dict[str, Any]]:
        return {
            r: {
                "nees_median": num(c.nees_median),
                "nees_mean": num(c.nees_mean),
                "coverage95": num(c.coverage),
            }
            for r, c in self.robots.items()
        }

    def cells(self, robot: str) -> dict[str, str]:
        c = self.robots.get(robot)
        return (
            {}
            if c is None
            else {"NEES": f"{c.nees_median:.2f}", "95 % cov.": f"{100 * c.coverage:.0f} %"}
        )


@register_metric
class Nees(Metric):
    """Whether the published covariances cover the error: NEES and 95 % coverage."""

    name = "consistency"
    columns = (Column("NEES", 60), Column("95 % cov.", 61))
    caption = NEES_CAPTION

    def compute(self, run: MethodRun) -> ConsistencyResult:
        if run.aligned:
            return ConsistencyResult({})
        return ConsistencyResult(
            consistency(run.estimates, run.truth, run.robots, run.start, run.rotation)
        )


# ---------------------------------------------------------------------------- shapes
@dataclass(frozen=True)
class ShapeResult(MetricResult):
    stats: dict[str, ApeStats] = field(default_factory=dict)
    """Where the orientation was unobservable after the warm-up: the APE of those estimates'
    published shapes after one rotation/reflection fitted for them all."""
    unobservable_fraction: float = math.nan
    """Fraction of the estimates after the warm-up with ``orientation_observable`` False."""
    observable_from_s: float = math.nan
    """Seconds from the start of the run to the estimate from which the orientation stays
    observable to the end (nan: never)."""
    paired: dict[str, Paired] = field(default_factory=dict, repr=False, compare=False)
    """The shapes behind ``stats``, aligned as scored (what the trajectory plot draws)."""

    def robot_json(self) -> dict[str, dict[str, Any]]:
        return {
            r: {
                "shape_ape_median": num(s.median),
                "shape_ape_rmse": num(s.rmse),
                "shape_ape_max": num(s.max),
            }
            for r, s in self.stats.items()
        }

    def method_json(self) -> dict[str, Any]:
        if not math.isfinite(self.unobservable_fraction):
            return {}
        return {
            "orientation_unobservable_fraction": num(self.unobservable_fraction),
            "orientation_observable_from_s": num(self.observable_from_s),
        }

    def tables(self, scenario: str, method: str) -> list[Table]:
        if not self.stats:
            return []
        table = Table(
            title=(
                f"{scenario} / {method}: formation orientation unobservable in "
                f"{100 * self.unobservable_fraction:.0f} % of the estimates after the warm-up; "
                "shape APE after one rotation/reflection for the run"
            )
        )
        for col in ("robot", "shape APE median", "rmse", "max", "n"):
            table.add_column(col, justify="left" if col == "robot" else "right")
        for robot, s in sorted(self.stats.items()):
            table.add_row(robot, f"{s.median:.3f}", f"{s.rmse:.3f}", f"{s.max:.3f}", str(s.n))
        return [table]


@register_metric
class ShapeApe(Metric):
    """The orientation flag's history and, where the orientation was unobservable, the shape
    APE after one alignment for those estimates (a moving formation's gauge turns with it)."""

    name = "shape"
    table_group = 1

    def compute(self, run: MethodRun) -> ShapeResult:
        late = [e for e in run.estimates if e.t >= run.start]
        if run.aligned or not late:
            return ShapeResult()
        flags = np.array([e.orientation_observable for e in run.estimates])
        fraction = float(np.mean([not e.orientation_observable for e in late]))
        bad = np.flatnonzero(~flags)
        observable_from = math.nan
        if bad.size == 0:
            observable_from = 0.0
        elif bad[-1] + 1 < len(run.estimates):
            observable_from = float(run.estimates[bad[-1] + 1].t - run.t0)
        shaped: dict[str, Paired] = {}
        if fraction > 0.0:
            hidden = [e for e in late if not e.orientation_observable]
            aligned = align(associate_shapes(hidden, run.truth, run.robots, run.rotation), "run")
            shaped = {r: after(q, run.start) for r, q in aligned.items()}
        stats = {r: ApeStats.of(q.errors) for r, q in shaped.items()}
        return ShapeResult(stats, fraction, observable_from, shaped)


@dataclass(frozen=True)
class FinalShapeResult(MetricResult):
    shape: dict[str, Any]
    """The last estimate's shape in its gauge, pairwise distances, flag and status."""

    def method_json(self) -> dict[str, Any]:
        return {"final_shape": self.shape} if self.shape else {}


@register_metric
class FinalShape(Metric):
    """The last published shape (methods that report one, unaligned)."""

    name = "final_shape"

    def compute(self, run: MethodRun) -> FinalShapeResult:
        if run.aligned or not run.estimates or not run.estimates[-1].shape:
            return FinalShapeResult({})
        last = run.estimates[-1]
        return FinalShapeResult(
            {
                "t": last.t,
                "orientation_observable": last.orientation_observable,
                "mode_weight": num(last.mode_weight),
                "n_modes": last.n_modes,
                "gauge": last.shape_gauge,
                "shape": {r: [num(v) for v in p] for r, p in last.shape.items()},
                "distances": {p: [num(m), num(s)] for p, (m, s) in last.distances.items()},
                "status": last.status,
            }
        )


# ---------------------------------------------------------------------------- particles, unseen
@dataclass(frozen=True)
class ParticlesResult(MetricResult):
    counts: dict[str, Any]

    def method_json(self) -> dict[str, Any]:
        return {"particles": self.counts} if self.counts else {}


@register_metric
class ParticleCounts(Metric):
    """The particle count over time (:func:`particle_counts`)."""

    name = "particles"

    def compute(self, run: MethodRun) -> ParticlesResult:
        return ParticlesResult(particle_counts(run.estimates, run.t0, run.warmup))


def particle_counts(estimates: Any, t0: float, warmup: float) -> dict[str, Any]:
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


@dataclass(frozen=True)
class UnseenResult(MetricResult):
    intervals: dict[str, list[list[float]]]

    def method_json(self) -> dict[str, Any]:
        return {"unseen": self.intervals} if self.intervals else {}


@register_metric
class Unseen(Metric):
    """When the estimates listed a robot as unseen (:func:`unseen_intervals`)."""

    name = "unseen"

    def compute(self, run: MethodRun) -> UnseenResult:
        return UnseenResult(unseen_intervals(run.estimates, run.t0))


def unseen_intervals(estimates: Any, t0: float) -> dict[str, list[list[float]]]:
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
