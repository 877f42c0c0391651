"""The scaling table of docs/explanation/scaling.md: the ``grid`` scenario for several team sizes, the
sampled particle filter against the range-graph Gaussian sum, with multilateration.

For every team size and representation it prints the APE median over robots (the median of
each robot's APE median after the 10 s warm-up) and the worst robot's, the compute time of the
localizer for the 40 s run, the median 95 % coverage of the published covariance, the median
rotation of the estimate against the truth (the one rotation about the reference that best
maps the true formation onto the estimate, over the estimates after the warm-up) and the
APE after that rotation (what the shape alone is worth). Two experiments on the cause of that
rotation: ``--no-heading-error`` runs the same grid with the simulator's heading-dependent
range error switched off; ``--alternate-directions`` keeps the error but has every second
robot drive its circle clockwise (an experiment of this script: the demo's grid is unchanged).

    PYTHONPATH=src python scripts/grid_scaling.py --robots 5,10,20,50 --representations graph
    PYTHONPATH=src python scripts/grid_scaling.py --robots 5,10 --representations sampled --particles 20000
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

import numpy as np

from relloc.config import TeamConfig
from relloc.engine import Engine, Pipeline
from relloc.estimators.particle.localizer import ParticleFilterLocalizer
from relloc.estimators.range_graph.localizer import RangeGraphLocalizer
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.localizers.multilateration import MultilaterationLocalizer
from relloc.simulator import scenarios
from relloc.simulator.error_models import UwbErrorModel
from relloc.simulator.kinematics import circle_loop
from relloc.simulator.scenarios import grid_scenario

WARMUP = 10.0


class GraphStartedParticles(ParticleFilterLocalizer):
    """The alternative: the sampled filter, its particles drawn from the range-graph start's
    Gaussians (each of the 72 orientation hypotheses equally likely) instead of annealed from
    the uniform prior; everything after the start is the sampled filter's."""

    def _start(self, t: float, batch: list[Any]) -> Any:
        graph = RangeGraphLocalizer(self.config)
        if not graph._start_from(batch):
            return None
        f, pf = graph.filter, self.filter
        pick = self.rng.integers(0, f.n, pf.n)
        chol = np.linalg.cholesky(f.cov)
        noise = np.einsum(
            "mde,me->md", chol[pick], self.rng.standard_normal((pf.n, f.mean.shape[1]))
        )
        pf.particles[:, : f.mean.shape[1]] = f.mean[pick] + noise
        pf.logw = np.full(pf.n, -np.log(pf.n))
        self._started(t)
        return self._emit(t, pf.estimate())


def localizer(name: str, config: TeamConfig, seed: int) -> Any:
    if name == "graph":
        return RangeGraphLocalizer(config, seed=seed)
    if name == "sampled_graph_start":
        return GraphStartedParticles(config, seed=seed)
    if name == "sampled":
        return ParticleFilterLocalizer(config, seed=seed)
    return MultilaterationLocalizer(config, seed=seed)


def rotation_stats(estimates: list[Any], sim: Any) -> tuple[float, float]:
    """Median rotation (deg) of the estimates after the warm-up against the truth, and the
    median over robots of the APE median after removing each estimate's rotation."""
    others = [r for r in sim.robots if r != sim.reference]
    angles, errors = [], []
    for e in estimates:
        if e.t < WARMUP:
            continue
        t = np.array([e.t])
        ref = sim.true_poses(sim.reference, t)[0, :2]
        true = np.array([sim.true_poses(r, t)[0, :2] - ref for r in others])
        est = np.array([e.positions[r] for r in others])
        h = true.T @ est
        a = float(np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
        c, s = np.cos(-a), np.sin(-a)
        back = est @ np.array([[c, s], [-s, c]])
        angles.append(np.degrees(a))
        errors.append(np.linalg.norm(back - true, axis=1))
    if not errors:
        return float("nan"), float("nan")
    per_robot = np.median(np.array(errors), axis=0)
    return float(np.median(angles)), float(np.median(per_robot))


def alternating_circles() -> Any:
    """A ``circle_loop`` that makes every second circle it is asked for clockwise."""
    count = [0]

    def loop(cx: float, cy: float, radius: float, speed: float) -> Any:
        count[0] += 1
        start, segments = circle_loop(cx, cy, radius, speed)
        if count[0] % 2 == 0:
            return start, segments
        x, y, yaw = start
        return (x, y, yaw - np.pi), [(d, v, -w) for d, v, w in segments]

    return loop


def run(
    n: int,
    representation: str,
    seed: int,
    particles: int,
    heading_error: bool,
    multilateration: bool = True,
    alternate: bool = False,
) -> dict[str, Any]:
    uwb = None if heading_error else UwbErrorModel(orientation_amplitude=0.0)
    if alternate:
        original, scenarios.circle_loop = scenarios.circle_loop, alternating_circles()
        try:
            sim = grid_scenario(seed, robots=n, uwb=uwb)
        finally:
            scenarios.circle_loop = original
    else:
        sim = grid_scenario(seed, robots=n, uwb=uwb)
    config = sim.config.with_filter(particles=particles)
    pipelines = [Pipeline("pf", localizer(representation, config, seed))]
    if multilateration:
        pipelines.append(Pipeline("multilateration", localizer("m", config, seed)))
    gt = GroundTruth(config.reference)
    engine = Engine(pipelines, truth_sinks=[gt.add])
    estimates: list[Any] = []
    start = time.perf_counter()
    for event in sim.events():
        for est in engine.feed(event):
            if est.method == "pf":
                estimates.append(est)
    engine.finish()
    wall = time.perf_counter() - start
    report = evaluate(engine, gt, "grid", WARMUP)
    out: dict[str, Any] = {"robots": n, "representation": representation, "wall_s": wall}
    for method, mr in report.methods.items():
        meds = [s.median for s in mr.robots.values() if s.n]
        out[method] = {
            "median": statistics.median(meds),
            "worst": max(meds),
            "compute_s": mr.compute_s,
        }
        cov = [c.coverage for c in mr.consistency.values()]
        if cov:
            out[method]["coverage"] = statistics.median(cov)
            out[method]["nees"] = statistics.median(c.nees_median for c in mr.consistency.values())
    out["rotation_deg"], out["aligned"] = rotation_stats(estimates, sim)
    out["stats"] = {
        k: v for k, v in pipelines[0].localizer.stats.items() if "hypoth" in k or "diverg" in k
    }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="5,10,20")
    ap.add_argument(
        "--representations",
        default="graph",
        help="comma-separated: graph, sampled, sampled_graph_start",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--particles", type=int, default=20000, help="the sampled filter's particles")
    ap.add_argument(
        "--no-heading-error",
        action="store_true",
        help="the grid without the heading-dependent range error",
    )
    ap.add_argument(
        "--alternate-directions", action="store_true", help="every second robot circles clockwise"
    )
    ap.add_argument(
        "--no-multilateration", action="store_true", help="skip multilateration (slow at 50 robots)"
    )
    args = ap.parse_args()
    print(
        "robots repr     PF median/worst  multilat  compute  coverage  NEES  rotation  aligned  stats"
    )
    for n in (int(v) for v in args.robots.split(",")):
        for rep in args.representations.split(","):
            r = run(
                n,
                rep,
                args.seed,
                args.particles,
                not args.no_heading_error,
                not args.no_multilateration,
                args.alternate_directions,
            )
            pf, ml = r["pf"], r.get("multilateration", {"median": float("nan")})
            print(
                f"{n:6d} {rep:8s} {pf['median']:.3f} / {pf['worst']:.3f}   {ml['median']:.3f}    "
                f"{pf['compute_s']:6.1f} s  {pf.get('coverage', float('nan')):5.0%}  {pf.get('nees', float('nan')):5.2f}  "
                f"{r['rotation_deg']:+5.2f}   {r['aligned']:.3f}  {r['stats']}",
                flush=True,
            )


if __name__ == "__main__":
    main()
