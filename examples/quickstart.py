"""Quick start: localize a simulated two-robot team from one UWB range and odometry.

Runs the library the way a user would: a source (the simulator), one pipeline (the particle
filter), the engine, and the evaluation against ground truth. ``tests/test_examples.py`` runs
every example, so this file cannot silently rot.

    .venv/bin/python examples/quickstart.py
"""

from __future__ import annotations

from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate, print_table
from relloc.methods import build_pipeline
from relloc.simulator import single_scenario


def main(particles: int = 5000) -> float:
    sim = single_scenario(seed=1, duration=30.0)
    config = sim.config.with_filter(particles=particles)
    gt = GroundTruth(config.reference)
    engine = Engine([build_pipeline("pf", config, seed=1)], truth_sinks=[gt.add])
    engine.run(sim.events())
    report = evaluate(engine, gt, "quickstart", warmup=10.0)
    print_table(report)
    last = engine.pipelines[0].estimates[-1]
    x, y = last.positions["r1"]
    print(f"last estimate: r1 at ({x:.2f}, {y:.2f}) m from r0, std {last.std('r1'):.2f} m")
    return report.methods["pf"].robots["r1"].median


if __name__ == "__main__":
    main()
