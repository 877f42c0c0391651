"""Time one range-error prediction per variant with onnxruntime on one core.

Usage::

    python benchmarks/ranging_inference.py [--models models/ranging] [--n 2000] [--json FILE]

For every model directory under ``--models`` (one per variant, written by ``relloc ranging
train``) it times, on one CPU core (the process is pinned to it where the OS allows) and one
onnxruntime thread:

* ``onnx``: ``PairModel.predict`` on one prebuilt window (the model alone, as the paper's
  "compute time per prediction");
* ``stage``: ``RangeCorrector.correct`` on a new range with a full window (what the engine pays
  per range: window bookkeeping, heading lookup, the prediction and the new event).

It prints the median (and 90th percentile) per prediction. The budget is 2 ms per window. With
``--untrained`` (or when no trained models exist and torch is installed) it times freshly
exported models of the default architectures instead: the cost does not depend on the weights.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from relloc.events import RangeEvent
from relloc.ranging.inference import ModelSet
from relloc.ranging.manifest import find_model_dirs, write_manifest
from relloc.stages.range_correction import RangeCorrector

BUDGET_S = 2e-3


def pin_to_one_core() -> str:
    """Restrict this process to one CPU (Linux); returns a description."""
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"cpu {cpu}"
    return "not pinned (no sched_setaffinity)"


def untrained_dirs(root: Path) -> list[Path]:
    """Default-architecture models with random weights, one directory per variant."""
    import torch

    from relloc.ranging.export import export_model
    from relloc.ranging.models import VARIANTS, Architecture, RangeErrorModel

    torch.set_num_threads(1)
    torch.manual_seed(0)
    dirs = []
    for variant in VARIANTS:
        d = root / variant
        d.mkdir(parents=True)
        model = RangeErrorModel(Architecture(variant), n_steps=10)
        export_model(model, d / "n_3-n_7.onnx")
        write_manifest(
            d,
            {
                "variant": variant,
                "n_steps": 10,
                "pairs": {
                    "n_3-n_7": {
                        "nodes": ["n_3", "n_7"],
                        "onnx": "n_3-n_7.onnx",
                        "train_bias": 0.3,
                        "residual_min": -1.0,
                        "residual_max": 1.0,
                    }
                },
            },
        )
        dirs.append(d)
    return dirs


def time_calls(fn, n: int) -> list[float]:  # type: ignore[no-untyped-def]
    """Wall time of ``n`` calls of ``fn(i)`` after 50 warm-up calls."""
    for i in range(50):
        fn(i)
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out.append(time.perf_counter() - t0)
    return out


def bench(models: ModelSet, n: int, seed: int = 0) -> dict[str, dict[str, float]]:
    """Timings of the model alone and of the stage, seconds per prediction."""
    rng = np.random.default_rng(seed)
    pair = next(iter(models))
    model = models[pair]
    steps = models.n_steps
    windows = np.stack(
        [
            4.0 + 0.05 * rng.standard_normal((256, steps)),
            rng.uniform(-np.pi, np.pi, (256, steps)),
            rng.uniform(-np.pi, np.pi, (256, steps)),
        ],
        axis=-1,
    ).astype(np.float32)
    onnx = time_calls(lambda i: model.predict_raw(windows[i % 256 : i % 256 + 1]), n)

    node_a, node_b = model.nodes
    corrector = RangeCorrector(models, max_yaw_age=None, max_gap=None)
    corrector.set_yaw("robot_a", 0.0, 0.3)
    corrector.set_yaw("robot_b", 0.0, -1.2)
    calls = iter(range(10**9))

    def correct(_: int) -> None:
        i = next(calls)  # a new time and a new distance on every call: each one predicts
        event = RangeEvent(0.1 * i, "robot_a", "robot_b", 4.0 + 0.01 * i, node_a, node_b)
        corrector.correct(event)

    for i in range(steps):  # fill the window
        correct(i)
    stage = time_calls(correct, n)
    # Every timed call predicted (the window filled on the last fill call).
    assert corrector.stats["corrected"] == n + 51, corrector.stats
    return {name: _summary(t) for name, t in (("onnx", onnx), ("stage", stage))}


def _summary(times: list[float]) -> dict[str, float]:
    return {
        "median": statistics.median(times),
        "p90": float(np.percentile(times, 90)),
        "mean": statistics.fmean(times),
        "n": len(times),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=["models/ranging"])
    parser.add_argument("--n", type=int, default=2000, help="timed predictions per variant")
    parser.add_argument("--untrained", action="store_true", help="time random-weight models")
    parser.add_argument("--json", help="write the timings here")
    args = parser.parse_args(argv)
    core = pin_to_one_core()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            dirs = [] if args.untrained else find_model_dirs(args.models)
        except ValueError as exc:
            print(f"no trained models ({exc}); timing untrained ones", file=sys.stderr)
            dirs = []
        if not dirs:
            dirs = untrained_dirs(Path(tmp))
        results = {}
        for d in dirs:
            models = ModelSet.load(d, threads=1)
            results[models.variant] = {"directory": str(d), **bench(models, args.n)}
    import onnxruntime

    print(f"one-window range-error prediction, onnxruntime {onnxruntime.__version__}, {core}")
    print(f"{'variant':<10} {'onnx median':>12} {'onnx p90':>10} {'stage median':>13}")
    for variant, r in results.items():
        print(
            f"{variant:<10} {r['onnx']['median'] * 1e3:>9.3f} ms {r['onnx']['p90'] * 1e3:>7.3f} ms"
            f" {r['stage']['median'] * 1e3:>10.3f} ms"
        )
    worst = max(r["stage"]["median"] for r in results.values())
    verdict = "within" if worst <= BUDGET_S else "OVER"
    print(
        f"slowest stage median {worst * 1e3:.3f} ms: {verdict} the {BUDGET_S * 1e3:.0f} ms budget"
    )
    if args.json:
        Path(args.json).write_text(
            json.dumps({"core": core, "budget_s": BUDGET_S, "variants": results}, indent=2) + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
