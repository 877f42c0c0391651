"""A new metric is one class: registered, it shows in every method's JSON and in the APE table
with no other edit (a toy: the share of estimates within 0.2 m after the warm-up)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from rich.console import Console

from relloc.engine import Engine
from relloc.evaluation import metric
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate, print_table
from relloc.methods import build_pipeline
from relloc.simulator import single_scenario


@dataclass(frozen=True)
class WithinResult(metric.MetricResult):
    share: dict[str, float]

    def robot_json(self) -> dict[str, dict[str, Any]]:
        return {r: {"within_20cm": metric.num(v)} for r, v in self.share.items()}

    def method_json(self) -> dict[str, Any]:
        return {"within_20cm_worst": metric.num(min(self.share.values(), default=float("nan")))}

    def cells(self, robot: str) -> dict[str, str]:
        return {"within 0.2 m": f"{100 * self.share[robot]:.0f} %"} if robot in self.share else {}


class Within20cm(metric.Metric):
    name = "within_20cm"
    columns = (metric.Column("within 0.2 m"),)

    def compute(self, run: metric.MethodRun) -> WithinResult:
        return WithinResult(
            {r: float(np.mean(q.errors <= 0.2)) for r, q in run.late.items() if len(q.t)}
        )


def test_a_registered_metric_shows_in_the_json_and_the_table(
    request: pytest.FixtureRequest,
) -> None:
    sim = single_scenario(seed=0, duration=30.0)
    config = sim.config.with_filter(particles=1000)
    gt = GroundTruth(config.reference)
    engine = Engine(
        [build_pipeline(m, config, seed=0) for m in ("pf", "multilateration")], truth_sinks=[gt.add]
    )
    engine.run(sim.events())
    before = evaluate(engine, gt, "single", warmup=10.0).to_json()

    metric.register_metric(Within20cm)
    request.addfinalizer(lambda: metric.METRICS.remove(Within20cm))
    report = evaluate(engine, gt, "single", warmup=10.0)
    after = report.to_json()

    pf = report.methods["pf"]
    late = pf.paired["r1"].errors[pf.paired["r1"].t >= report.t0 + 10.0]
    share = round(float(np.mean(late <= 0.2)), 5)
    assert after["methods"]["pf"]["robots"]["r1"]["within_20cm"] == share
    assert after["methods"]["pf"]["within_20cm_worst"] == share
    assert "within_20cm" not in after["methods"]["multilateration"]["robots"]["r1"]  # no estimate
    # nothing else changed
    for method, fig in after["methods"].items():
        fig.pop("within_20cm_worst")
        for entry in fig["robots"].values():
            entry.pop("within_20cm", None)
        fig.pop("compute_s"), before["methods"][method].pop("compute_s")
    assert after == before

    console = Console(record=True, width=200)
    print_table(report, console)
    text = console.export_text()
    header = next(line for line in text.splitlines() if "APE median" in line)
    assert header.rstrip(" ┃").endswith("within 0.2 m")  # a new column goes last
    row = next(line for line in text.splitlines() if line.startswith("│ pf "))
    assert row.rstrip(" │").endswith(f"{100 * share:.0f} %")
