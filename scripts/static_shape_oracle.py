"""How well could *any* range-only estimator know a parked team's shape? An oracle on the
``static`` scenario of ``relloc demo``.

A parked pair's UWB error is constant for the whole run: its bias, plus the heading-dependent
antenna term at the two fixed headings, plus white noise and NLOS spikes. The oracle knows each
pair's true bias (as the demo's config does), takes each pair's median range over the run
(which drops the spikes and averages the noise), subtracts the bias and solves the
least-squares formation about the reference; the shape error per robot is the distance to the
truth after one rotation/reflection about the reference (the treatment ``relloc demo`` gives
the published shape). What is left is the antenna term, which nothing in the data can tell
from the geometry while the team is parked: a floor for every estimator that is not told it.

    .venv/bin/python scripts/static_shape_oracle.py --seeds 0 1 2 3 4
"""

from __future__ import annotations

import argparse

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from relloc.evaluation.metrics import orthogonal_procrustes
from relloc.events import RangeEvent, pair_key
from relloc.simulator.scenarios import static_scenario

FloatArray = NDArray[np.float64]


def shape_errors(seed: int) -> dict[str, float]:
    """Per non-reference robot, the oracle's shape error (m) on ``static_scenario(seed)``."""
    sim = static_scenario(seed)
    ref = sim.reference
    others = [r for r in sim.robots if r != ref]
    mid = 0.5 * sim.duration
    truth = np.array(
        [np.subtract(sim.true_pose(r, mid)[:2], sim.true_pose(ref, mid)[:2]) for r in others]
    )
    ranges: dict[tuple[str, str], list[float]] = {}
    for e in sim.events():
        if isinstance(e, RangeEvent):
            ranges.setdefault((e.robot_a, e.robot_b), []).append(e.distance)
    pairs = sorted(ranges)
    bias = [
        sim.true_biases[pair_key(*sim.config.range_nodes(RangeEvent(0.0, a, b, 0.0)))]
        for a, b in pairs
    ]
    measured = np.array([np.median(ranges[p]) for p in pairs]) - np.array(bias)
    index = {r: k for k, r in enumerate(others)}

    def position(x: FloatArray, robot: str) -> FloatArray:
        return np.zeros(2) if robot == ref else x[2 * index[robot] : 2 * index[robot] + 2]

    def residuals(x: FloatArray) -> FloatArray:
        return (
            np.array([np.linalg.norm(position(x, a) - position(x, b)) for a, b in pairs]) - measured
        )

    # Started near the truth: the oracle asks how good the best fit is, not whether one is found.
    fit = least_squares(residuals, truth.reshape(-1) + 0.2).x.reshape(-1, 2)
    turn = orthogonal_procrustes(fit, truth)  # a rotation or a reflection about the reference
    errors = np.linalg.norm(fit @ turn.T - truth, axis=1)
    return dict(zip(others, errors.tolist(), strict=True))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    args = ap.parse_args(argv)
    for seed in args.seeds:
        errors = shape_errors(seed)
        print(f"seed {seed}: " + "  ".join(f"{r} {e:.3f}" for r, e in errors.items()))


if __name__ == "__main__":
    main()
