"""The sampled filter's online bias (``--bias online``) against the default bias on new sessions.

A session of the ``single`` scenario (``r0`` static and the reference, ``r1`` circling, one
range) is drawn with a chosen true pair bias and a chosen odometry scale error (``r1``'s path
short by that fraction, like the TIERS recordings' 7-9 %); the filter's config carries no pair
calibration, as on ``pair_range_20220907_1725``. Each session is run twice, with the default
bias (``uwb.default_bias`` 0.3 m widened by ``default_bias_sigma``) and with ``--bias online``,
and the APE median of ``r1`` after the warm-up is printed for both (plus the final online bias
and the session's median of range - true distance, the bias a bag's motion capture would score).
``--duration`` lengthens the session; ``--orientation 0`` switches the heading-dependent range
error off, which is what drives a long session's online bias away from that median.

    PYTHONPATH=src .venv/bin/python scripts/online_bias_sessions.py --biases 0.1,0.3,0.5 \
        --scales 0,0.08 --seeds 0-2 --particles 5000

``--set key=value`` changes a filter parameter (``FilterConfig.with_changes``, e.g.
``bias_walk=0.002``, ``kind=gaussian_sum``) for the online run only, to compare variants of the
online bias (the sampled filter's prior width of an uncalibrated pair is
``uwb.default_bias_sigma``, not a filter parameter). Figures: docs/explanation/self-calibration.md, "Online bias on a new session".
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from relloc.cli import argtypes
from relloc.config import TeamConfig
from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.events import GroundTruthEvent, RangeEvent
from relloc.methods import build_pipeline
from relloc.simulator import single_scenario
from relloc.simulator.error_models import OdometryErrorModel, UwbErrorModel


def session(
    seed: int,
    bias: float,
    scale_error: float,
    duration: float = 45.0,
    orientation: float | None = None,
) -> tuple[object, TeamConfig]:
    """The simulation and the config a user would have: no pair calibration. ``orientation``:
    the heading-dependent range error's amplitude (``None``: the simulator's default)."""
    uwb = UwbErrorModel(bias_range=(bias, bias))
    if orientation is not None:
        uwb = replace(uwb, orientation_amplitude=orientation)
    sim = single_scenario(
        seed,
        duration=duration,
        uwb=uwb,
        odometry=OdometryErrorModel(scale_range=(1.0 - scale_error, 1.0 - scale_error)),
    )
    config = replace(sim.config, uwb=replace(sim.config.uwb, pairs={}))
    return sim, config


def median_range_error(sim: object) -> float:
    """The session's median of range - true distance: the pair's bias as a bag's motion capture
    scores it (the drawn bias plus what the heading-dependent error adds over this session)."""
    where: dict[str, tuple[float, float]] = {}
    errors = []
    for ev in sim.events():  # type: ignore[attr-defined]
        if isinstance(ev, GroundTruthEvent):
            where[ev.robot] = (ev.position[0], ev.position[1])
        elif isinstance(ev, RangeEvent) and ev.robot_a in where and ev.robot_b in where:
            (xa, ya), (xb, yb) = where[ev.robot_a], where[ev.robot_b]
            errors.append(ev.distance - float(np.hypot(xa - xb, ya - yb)))
    return float(np.median(errors))


def ape_median(sim: object, config: TeamConfig, seed: int, warmup: float) -> tuple[float, float]:
    """APE median of every non-reference robot (the worst), and the final online bias (nan if
    the bias is not estimated)."""
    pipeline = build_pipeline("pf", config, seed=seed)
    gt = GroundTruth(config.reference)
    engine = Engine([pipeline], truth_sinks=[gt.add])
    engine.run(sim.events())  # type: ignore[attr-defined]
    report = evaluate(engine, gt, "sim", warmup)
    method = report.methods["pf"]
    final = next(iter(method.final_biases.values()), (float("nan"), 0.0))[0]
    return max(s.median for s in method.robots.values()), final


def _values(text: str) -> list[float]:
    return [float(v) for v in text.split(",")]


def _parse_set(items: list[str]) -> dict[str, object]:
    out: dict[str, object] = {}
    for item in items:
        key, value = item.split("=", 1)
        out[key] = (
            value if not value.replace(".", "", 1).replace("-", "", 1).isdigit() else float(value)
        )
    return out


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--biases", default="0.1,0.3,0.5")
    p.add_argument(
        "--scales", default="0,0.08", help="odometry scale errors (path short by this fraction)"
    )
    p.add_argument(
        "--seeds", type=argtypes.seeds, default="0-2", help="LO-HI or a comma-separated list"
    )
    p.add_argument("--particles", type=int, default=5000)
    p.add_argument("--warmup", type=float, default=10.0)
    p.add_argument("--duration", type=float, default=45.0, help="session length (s)")
    p.add_argument(
        "--orientation",
        type=float,
        default=None,
        help="amplitude of the heading-dependent range error (m); 0 switches it off",
    )
    p.add_argument("--set", action="append", default=[], help="filter parameter for the online run")
    p.add_argument("--skip-default", action="store_true")
    args = p.parse_args()
    changes = _parse_set(args.set)
    print(
        "| seed | true bias | session median error | scale error | default APE | online APE | online - default | final bias |"
    )
    print("|---|---|---|---|---|---|---|---|")
    diffs = []
    for bias in _values(args.biases):
        for scale in _values(args.scales):
            for seed in args.seeds:
                sim, config = session(seed, bias, scale, args.duration, args.orientation)
                config = config.with_filter(particles=args.particles)
                d = float("nan")
                if not args.skip_default:
                    d, _ = ape_median(sim, config, seed, args.warmup)
                online = config.with_modes(bias="online").with_filter(**changes)
                o, b = ape_median(sim, online, seed, args.warmup)
                diffs.append(o - d)
                print(
                    f"| {seed} | {bias:.2f} | {median_range_error(sim):.3f} | {scale:.2f} | {d:.3f} | {o:.3f} | {o - d:+.3f} | {b:.3f} |",
                    flush=True,
                )
    arr = np.array(diffs)
    if not args.skip_default:
        print(f"online - default: max {np.nanmax(arr):+.3f}, median {np.nanmedian(arr):+.3f}")


if __name__ == "__main__":
    main()
