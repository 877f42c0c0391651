"""Time relloc's fast CDR codecs against ``rosbags`` on the live engine's hot messages.

Usage::

    python benchmarks/cdr_codecs.py [--n 20000] [--rounds 5] [--json FILE] [--readme FILE]

For each message the live engine handles per sample (decoding a ``nav_msgs/Odometry`` or a
``sensor_msgs/Range`` into the fields relloc uses; encoding a ``PoseWithCovarianceStamped``
estimate) it times ``relloc.ros.cdr`` and the ``rosbags`` path it replaces (deserialise or
build + serialise the message object) on the same payloads, alternating the two in every round,
and prints the median time per message and the ratio. Both produce the same values (asserted
once before timing). This is a warm tight loop: in the server, which sleeps between messages,
both cost more, and the rosbags path more so (see ``docs/explanation/live-engine.md``). ``--readme FILE`` writes
the table of the run between the ``cdr_codecs`` figures markers of FILE (``relloc.evaluation.pages``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as dist_version
from pathlib import Path
from typing import Any

from relloc.evaluation.pages import missing_section, write_between
from relloc.events import OdometryEvent, RangeEvent
from relloc.ros import cdr as ros_cdr
from relloc.ros import messages as rm
from relloc.ros.estimate_msgs import pose_covariance


def _cases() -> dict[str, tuple[Callable[[], Any], Callable[[], Any]]]:
    odom = rm.encode(
        rm.odometry_msg(OdometryEvent(t=1.7e9, robot="a", x=1.0, y=2.0, yaw=0.3, v=0.2, w=0.1))
    )
    rng = rm.encode(rm.range_msg(RangeEvent(t=1.7e9, robot_a="a", robot_b="b", distance=3.2)))
    xy = [[0.04, 0.0], [0.0, 0.09]]
    cov = pose_covariance(xy)  # row-major 6x6: the x/y block, the rest not estimated

    def odom_rosbags() -> Any:
        msg = rm.decode(odom, rm.ODOMETRY)
        ev = rm.odometry_to_event(msg, "a")
        return rm.stamp_to_sec(msg.header.stamp), ev.x, ev.y, ev.yaw, ev.v, ev.w, ev.z

    def range_rosbags() -> Any:
        msg = rm.decode(rng, rm.RANGE)
        return rm.stamp_to_sec(msg.header.stamp), msg.range

    def pose_rosbags() -> bytes:
        return rm.encode(rm.pose_with_covariance_msg(1.7e9, 1.0, 2.0, cov=xy, frame_id="ref"))

    def pose_fast() -> bytes:
        return ros_cdr.encode_pose_with_covariance_stamped(1.7e9, 1.0, 2.0, 0.0, cov, "ref")

    return {
        "decode Odometry": (lambda: ros_cdr.decode_odometry(odom), odom_rosbags),
        "decode Range": (lambda: ros_cdr.decode_range(rng), range_rosbags),
        "encode PoseWithCovarianceStamped": (pose_fast, pose_rosbags),
    }


def _time(fn: Callable[[], Any], n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n


def figures_table(results: dict[str, dict[str, float]], context: str) -> str:
    """The Markdown table of one run (what ``--readme`` writes in section ``cdr_codecs``)."""
    lines = [
        f"Written by {context}:",
        "",
        "| message | relloc.ros.cdr | rosbags | ratio |",
        "|---|---:|---:|---:|",
    ]
    for name, r in results.items():
        lines.append(
            f"| {name} | {r['relloc_us']:.2f} µs | {r['rosbags_us']:.2f} µs | {r['speedup']:.1f}x |"
        )
    return "\n".join(lines)


def _rosbags_version() -> str:
    try:
        return dist_version("rosbags")
    except PackageNotFoundError:
        return "?"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=20000, help="messages per timed batch")
    p.add_argument("--rounds", type=int, default=5, help="alternating batches per codec")
    p.add_argument("--json", default=None, metavar="FILE")
    p.add_argument(
        "--readme",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the table into this Markdown file, between its cdr_codecs figures markers",
    )
    args = p.parse_args(argv)
    problem = None if args.readme is None else missing_section(args.readme, "cdr_codecs")
    if problem is not None:
        p.error(problem)
    results = {}
    for name, (fast, ref) in _cases().items():
        assert fast() == ref(), name  # same values (bytes) before anything is timed
        t_fast, t_ref = [], []
        for r in range(args.rounds):
            order = (fast, ref) if r % 2 == 0 else (ref, fast)
            for fn in order:
                (t_fast if fn is fast else t_ref).append(_time(fn, args.n))
        f, rb = statistics.median(t_fast), statistics.median(t_ref)
        results[name] = {"relloc_us": f * 1e6, "rosbags_us": rb * 1e6, "speedup": rb / f}
        print(f"{name:34s} relloc {f * 1e6:6.2f} us   rosbags {rb * 1e6:6.2f} us   {rb / f:5.1f}x")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(results, indent=2))
    if args.readme is not None:
        context = (
            f"`benchmarks/cdr_codecs.py --n {args.n} --rounds {args.rounds} --readme` (median per "
            f"message, warm tight loop; rosbags {_rosbags_version()}, Python {platform.python_version()}, "
            f"{os.cpu_count()} CPUs)"
        )
        write_between(args.readme, "cdr_codecs", figures_table(results, context))
        print(f"wrote the figures into {args.readme}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
