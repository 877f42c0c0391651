"""The formation scored after an alignment that the estimate does not choose.

Two metrics, JSON only, for every unaligned method (the filters, the smoother):

* :class:`RunAlignedApe`: one rotation/reflection about the reference fitted to all of the
  method's estimates after the warm-up (multilateration's fair alignment), like for like with
  the baseline; ``run_aligned_ape_median``.
* :class:`StepAlignedApe`: one fitted at every estimate, on the positions where the
  orientation is observable and on the published shape where it is not;
  ``step_aligned_ape_median``. Where nothing observes the formation's orientation it is a gauge
  at every instant: this compares estimators of such a team without charging that gauge's drift.

For a flying team's 3D estimates both fit a rotation/reflection about z only (the x-y gauge;
heights are measured, z is up for all): :func:`relloc.evaluation.metrics.orthogonal_procrustes`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from relloc.evaluation.metric import MethodRun, Metric, MetricResult, num, register_metric
from relloc.evaluation.metrics import ApeStats, Paired, after, align


@dataclass(frozen=True)
class RunAlignedResult(MetricResult):
    stats: dict[str, ApeStats] = field(default_factory=dict)
    """Per robot, the APE after the warm-up once one rotation/reflection about the reference,
    fitted to all of the method's estimates after the warm-up, is removed."""

    def robot_json(self) -> dict[str, dict[str, Any]]:
        return {r: {"run_aligned_ape_median": num(s.median)} for r, s in self.stats.items()}

    def method_json(self) -> dict[str, Any]:
        vals = [s.median for s in self.stats.values() if s.n]
        return {"mean_run_aligned_ape_median": num(float(np.mean(vals)))} if vals else {}


@register_metric
class RunAlignedApe(Metric):
    """The APE every method gets under multilateration's fair alignment (one orthogonal map for
    the run): what the estimate is worth as a formation, like for like with the baseline, beside
    the unaligned APE that also charges the filters for their absolute orientation. Of what the
    method publishes (:meth:`relloc.estimate.Estimate.published`: the formation in its gauge
    where the orientation is not observable, not the moments over the ring of orientations,
    which sit at the reference). JSON only."""

    name = "run_aligned"

    def compute(self, run: MethodRun) -> RunAlignedResult:
        if run.alignment == "step":
            return RunAlignedResult()
        late = run.late if run.aligned else align(_published_late(run), "run")
        return RunAlignedResult({r: ApeStats.of(q.errors) for r, q in late.items()})


@dataclass(frozen=True)
class StepAlignedResult(MetricResult):
    stats: dict[str, ApeStats] = field(default_factory=dict)
    """Per robot, the APE after the warm-up once the formation's rotation/reflection about the
    reference, fitted to the truth at every estimate, is removed."""

    def robot_json(self) -> dict[str, dict[str, Any]]:
        return {r: {"step_aligned_ape_median": num(s.median)} for r, s in self.stats.items()}

    def method_json(self) -> dict[str, Any]:
        vals = [s.median for s in self.stats.values() if s.n]
        return {"mean_step_aligned_ape_median": num(float(np.mean(vals)))} if vals else {}


@register_metric
class StepAlignedApe(Metric):
    """The formation scored per step: at every estimate one rotation/reflection about the
    reference fitted to the truth (an oracle alignment, as ``multilateration_oracle``'s), on the
    positions where the orientation is observable and on the published shape where it is not.
    Where nothing observes the orientation (no odometry, no compass) it is a gauge at every
    instant, so this is the figure that compares estimators of such a team; beside the shape APE
    aligned once for the run, which also charges the gauge's drift. JSON only."""

    name = "step_aligned"

    def compute(self, run: MethodRun) -> StepAlignedResult:
        if run.aligned:
            return StepAlignedResult()
        late = {r: q for r, q in _published_late(run).items() if len(q.t)}
        aligned = align(late, "step")
        return StepAlignedResult({r: ApeStats.of(q.errors) for r, q in aligned.items()})


def _published_late(run: MethodRun) -> dict[str, Paired]:
    """What the method published after the warm-up, paired with the truth (the shape where
    the orientation was not observable: :meth:`relloc.estimate.Estimate.published`)."""
    return {r: after(q, run.start) for r, q in run.published.items()}
