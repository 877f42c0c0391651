"""The formation scored without any alignment: its distances.

:class:`DistanceErrors`, for a flying team's 3D estimates: per robot, the median over the
estimates after the warm-up of ``| |p_i - p_j| - |g_i - g_j| |`` over its pairs (the
reference's included, at the origin), on what the method publishes. Distances are what ranges
measure: this is the shape's score where nothing observes the formation's orientation, not
even which way is up (a team with UWB alone, whose level tags leave "up" weakly observed), so
that no alignment, about z or otherwise, decides it. ``distance_error_median`` in the JSON.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from relloc.evaluation.metric import MethodRun, Metric, MetricResult, num, register_metric
from relloc.evaluation.metrics import after


@dataclass(frozen=True)
class DistanceResult(MetricResult):
    medians: dict[str, float] = field(default_factory=dict)
    """Per robot, the median error of its distances to the others (m)."""

    def robot_json(self) -> dict[str, dict[str, Any]]:
        return {r: {"distance_error_median": num(m)} for r, m in self.medians.items()}

    def method_json(self) -> dict[str, Any]:
        vals = list(self.medians.values())
        return {"mean_distance_error_median": num(float(np.mean(vals)))} if vals else {}


@register_metric
class DistanceErrors(Metric):
    """Each robot's distance errors to the others, 3D estimates only (module docstring)."""

    name = "distances"

    def compute(self, run: MethodRun) -> DistanceResult:
        late = {r: after(q, run.start) for r, q in run.published.items()}
        late = {r: q for r, q in late.items() if len(q.t)}
        if not late or next(iter(late.values())).est.shape[1] != 3:
            return DistanceResult()
        errors: dict[str, list[float]] = {r: [] for r in late}
        for t in sorted({float(t) for q in late.values() for t in q.t}):
            rows = {r: np.flatnonzero(q.t == t) for r, q in late.items()}
            here = {r: (late[r].est[i[0]], late[r].gt[i[0]]) for r, i in rows.items() if i.size}
            for r, (est, gt) in here.items():
                errors[r].append(abs(float(np.linalg.norm(est)) - float(np.linalg.norm(gt))))
                for other, (est2, gt2) in here.items():
                    if other != r:
                        d_est = float(np.linalg.norm(est - est2))
                        errors[r].append(abs(d_est - float(np.linalg.norm(gt - gt2))))
        return DistanceResult({r: float(np.median(e)) for r, e in errors.items() if e})
