"""The shipped metrics of self-calibration: published headings and odometry scales, and
online range biases, scored against the truth where it is known (:mod:`relloc.evaluation.metric`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rich.table import Table

from relloc.evaluation.metric import MethodRun, Metric, MetricResult, num, register_metric
from relloc.evaluation.selfcal_metrics import (
    HeadingPaired,
    associate_headings,
    bias_coverage,
    bias_errors,
)

FloatArray = NDArray[np.float64]


# ---------------------------------------------------------------------------- headings and scales
UNOBSERVABLE_SPREAD_DEG = 45.0
"""A published heading spread above this says: not observable yet (the robot has not moved)."""


@dataclass(frozen=True)
class HeadingsResult(MetricResult):
    headings: dict[str, HeadingPaired]
    """Heading-estimate mode: published relative headings against the truth, after the warm-up."""
    scales: dict[str, tuple[float, float]]
    """Online odometry scales: the last published (mean, std) per robot."""
    frame_rotation_deg: float | None = None
    """Heading-estimate mode: rotation of the reference's odometry frame in the mocap frame
    (its mocap yaw minus odometry yaw at its first odometry message), by which the ground
    truth is turned for evaluation."""

    def median_deg(self, robot: str) -> float:
        h = self.headings.get(robot)
        return math.degrees(float(np.median(h.errors))) if h is not None and len(h.t) else math.nan

    def spread_deg(self, robot: str) -> float:
        """Median published heading spread (circular std) after the warm-up (deg)."""
        h = self.headings.get(robot)
        return math.degrees(float(np.median(h.spread))) if h is not None and len(h.t) else math.nan

    def robot_json(self) -> dict[str, dict[str, Any]]:
        out: dict[str, dict[str, Any]] = {}
        for r in self.headings:
            out[r] = {
                "heading_median_deg": num(self.median_deg(r)),
                "heading_spread_deg": num(self.spread_deg(r)),
            }
        for r, (mean, std) in self.scales.items():
            out.setdefault(r, {}).update({"odom_scale": num(mean), "odom_scale_std": num(std)})
        return out

    def method_json(self) -> dict[str, Any]:
        return (
            {}
            if self.frame_rotation_deg is None
            else {"frame_rotation_deg": num(self.frame_rotation_deg)}
        )

    def tables(self, scenario: str, method: str) -> list[Table]:
        if not self.headings and not self.scales:
            return []
        table = Table(
            title=f"{scenario} / {method}: headings (reference's odometry frame) and odometry scales"
        )
        for col in ("robot", "heading", "spread", "heading error (median)", "scale"):
            table.add_column(col, justify="left" if col == "robot" else "right")
        for robot in sorted(set(self.headings) | set(self.scales)):
            h = self.headings.get(robot)
            cells = ["", "", ""]
            if h is not None and len(h.t):
                spread = math.degrees(float(h.spread[-1]))
                note = " (unobservable)" if spread > UNOBSERVABLE_SPREAD_DEG else ""
                cells = [
                    f"{math.degrees(float(h.mean[-1])):.1f} deg",
                    f"{spread:.1f} deg{note}",
                    f"{self.median_deg(robot):.2f} deg",
                ]
            scale = self.scales.get(robot)
            cells.append(
                ""
                if scale is None or not math.isfinite(scale[0])
                else f"{scale[0]:.3f} +- {scale[1]:.3f}"
            )
            table.add_row(robot, *cells)
        return [table]


@register_metric
class Headings(Metric):
    """Self-calibrated robot states: published relative headings scored against the truth
    (heading-estimate mode) and the last published odometry scales."""

    name = "headings"
    table_group = 2

    def compute(self, run: MethodRun) -> HeadingsResult:
        headings: dict[str, HeadingPaired] = {}
        if run.frame_rotation_deg is not None:
            pairs = associate_headings(run.estimates, run.truth, run.odometry_yaws, run.rotation)
            headings = {r: _after_heading(h, run.start) for r, h in pairs.items()}
        last = run.estimates[-1] if run.estimates else None
        scales = dict(last.scales) if last is not None else {}
        return HeadingsResult(headings, scales, run.frame_rotation_deg)


def _after_heading(h: HeadingPaired, t_start: float) -> HeadingPaired:
    keep = h.t >= t_start
    return HeadingPaired(h.t[keep], h.mean[keep], h.spread[keep], h.truth[keep])


# ---------------------------------------------------------------------------- online biases
@dataclass(frozen=True)
class BiasResult(MetricResult):
    final: dict[str, tuple[float, float]]
    """The last published (mean, std) per node pair."""
    truth: dict[str, float]
    errors: dict[str, FloatArray]
    """``|estimate - truth|`` per node pair after the warm-up (where a truth is known)."""
    covered: dict[str, FloatArray] = field(default_factory=dict)
    """Per node pair after the warm-up: whether each published 95 % interval held the truth."""

    def error_median(self, pair: str) -> float:
        e = self.errors.get(pair)
        return float(np.median(e)) if e is not None and e.size else math.nan

    def coverage(self, pair: str | None = None) -> float:
        """Share of the published 95 % intervals that held the truth: of ``pair``, or of every
        pair's together (``None``)."""
        parts = [self.covered[pair]] if pair in self.covered else []
        if pair is None:
            parts = list(self.covered.values())
        hits = np.concatenate(parts) if parts else np.zeros(0)
        return float(hits.mean()) if hits.size else math.nan

    def method_json(self) -> dict[str, Any]:
        if not self.final:
            return {}
        out: dict[str, Any] = {
            "pairs": {
                pair: {
                    "bias": num(mean),
                    "bias_std": num(std),
                    "bias_true": num(self.truth.get(pair, math.nan)),
                    "bias_error_median": num(self.error_median(pair)),
                    "bias_coverage95": num(self.coverage(pair)),
                }
                for pair, (mean, std) in self.final.items()
            }
        }
        if self.covered:
            out["bias_coverage95"] = num(self.coverage())
        return out

    def tables(self, scenario: str, method: str) -> list[Table]:
        if not self.final:
            return []
        table = Table(title=f"{scenario} / {method}: online range biases (m)")
        for col in ("pair", "bias", "std", "true", "error (median)", "95 % cov."):
            table.add_column(col, justify="left" if col == "pair" else "right")
        for pair, (mean, std) in sorted(self.final.items()):
            true = self.truth.get(pair)
            table.add_row(
                pair,
                f"{mean:.3f}",
                f"{std:.3f}",
                "" if true is None else f"{true:.3f}",
                "" if true is None else f"{self.error_median(pair):.3f}",
                "" if true is None else f"{self.coverage(pair):.0%}",
            )
        return [table]


@register_metric
class OnlineBiases(Metric):
    """Online range biases: the last published ones, scored against the truth where known."""

    name = "biases"
    table_group = 2

    def compute(self, run: MethodRun) -> BiasResult:
        last = run.estimates[-1] if run.estimates else None
        truth = {k: v for k, v in run.bias_truth.items() if last is not None and k in last.biases}
        return BiasResult(
            dict(last.biases) if last is not None else {},
            truth,
            bias_errors(run.estimates, dict(run.bias_truth), run.start),
            bias_coverage(run.estimates, dict(run.bias_truth), run.start),
        )
