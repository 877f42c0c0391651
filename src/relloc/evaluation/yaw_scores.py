"""Headings the tags show: each multi-tag robot's published yaw against the motion capture.

A robot with several UWB tags has its heading estimated (:attr:`relloc.estimate.Estimate.yaws`:
in the frame of the estimate, the reference's body frame where the reference has several tags).
:class:`YawError` pairs every published yaw after the warm-up with the truth in the same frame
(the robot's motion-capture yaw less the reference's in the body frame, less the frame's
rotation in the heading frame) and reports the median absolute error per robot in degrees:
``yaw_error_median_deg`` in the JSON, a column of the run table; the JSON has the mean as well
(``yaw_error_mean_deg``: the statistic published relative-pose figures give). A flying team's 3D estimates
publish every robot's yaw in the reference's yaw-only body frame (z up): scored the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from relloc.estimate import BODY_FRAME
from relloc.evaluation.metric import Column, MethodRun, Metric, MetricResult, num, register_metric


@dataclass(frozen=True)
class YawResult(MetricResult):
    errors_deg: dict[str, list[float]] = field(default_factory=dict)
    """Per robot, the absolute error of each published yaw after the warm-up (deg)."""

    def median(self, robot: str) -> float:
        values = self.errors_deg.get(robot, [])
        return float(np.median(values)) if values else math.nan

    def mean(self, robot: str) -> float:
        values = self.errors_deg.get(robot, [])
        return float(np.mean(values)) if values else math.nan

    def robot_json(self) -> dict[str, dict[str, Any]]:
        return {
            r: {
                "yaw_error_median_deg": num(self.median(r)),
                "yaw_error_mean_deg": num(self.mean(r)),
            }
            for r in self.errors_deg
        }

    def cells(self, robot: str) -> dict[str, str]:
        if not self.errors_deg.get(robot):
            return {}
        return {"yaw err. (deg)": f"{self.median(robot):.1f}"}


@register_metric
class YawError(Metric):
    """Median absolute error of each multi-tag robot's published heading (module docstring)."""

    name = "yaw_error"
    columns = (Column("yaw err. (deg)", 35, optional=True),)

    def compute(self, run: MethodRun) -> YawResult:
        out: dict[str, list[float]] = {}
        truth = run.truth
        for est in run.estimates:
            if est.t < run.start or not est.yaws:
                continue
            ref = truth.pose_at(truth.reference, est.t)
            for robot, (yaw, _) in est.yaws.items():
                pose = truth.pose_at(robot, est.t)
                if pose is None or ref is None:
                    continue
                frame = ref[2] if est.frame == BODY_FRAME else run.rotation
                error = math.remainder(yaw - (pose[2] - frame), math.tau)
                out.setdefault(robot, []).append(abs(math.degrees(error)))
        return YawResult(out)
