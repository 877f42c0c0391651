"""relloc serve on rmw_zenoh against an independent ROS 2 peer (zenoh-ros2-sdk), measured.

A clean simulated team (:mod:`relloc.live.peer_run`: the grid scenario, 4 robots, near-perfect
sensors) publishes its odometry and UWB ranges through the SDK with one distribution's message
definitions, written locally (the SDK never clones anything); ``relloc serve --ros-interface
rmw_zenoh --ros-distro ...`` runs as its own process on loopback; the SDK's subscribers collect
the poses it publishes. Printed: the poses per robot as the SDK received them, their APE median
against the simulator's truth (after ``--warmup``), and serve's rejection and transport
counters (from its ``--json`` summary)::

    .venv/bin/python scripts/ros2_peer_check.py --distro jazzy --duration 60
    .venv/bin/python scripts/ros2_peer_check.py --distro humble --serve-distro jazzy
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from relloc.live.peer_run import PeerRun, run_against_serve
from relloc.live.ros2_peer import STORES


def main(argv: list[str] | None = None) -> int:
    defaults = PeerRun()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--distro", choices=sorted(STORES), default="jazzy", help="the peer's definitions"
    )
    parser.add_argument(
        "--serve-distro", default=None, help="serve's --ros-distro (default: --distro)"
    )
    parser.add_argument("--duration", type=float, default=60.0, help="simulated seconds")
    parser.add_argument("--rate", type=float, default=1.0, help="simulated seconds per wall second")
    parser.add_argument("--robots", type=int, default=defaults.robots)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--particles", type=int, default=defaults.particles)
    parser.add_argument(
        "--reorder-window", type=float, default=defaults.reorder_window, help="serve's (s)"
    )
    parser.add_argument(
        "--warmup", type=float, default=defaults.warmup, help="simulated s left out of the APE"
    )
    parser.add_argument("--json", default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    run = PeerRun(
        distro=args.distro, serve_distro=args.serve_distro, seed=args.seed, robots=args.robots,
        duration=args.duration, rate=args.rate, particles=args.particles,
        reorder_window=args.reorder_window, warmup=args.warmup,
    )  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="ros2_peer_") as tmp:
        out = run_against_serve(run, Path(tmp))
    print(f"peer {out['distro']} -> relloc serve --ros-distro {out['serve_distro']}: "
          f"{len(out['robots'])} robots, {out['simulated_s']:g} simulated s at {out['rate']:g}x, "
          f"{out['sent']} messages on {out['publishers']} SDK publishers in {out['wall_s']} s "
          f"(max behind {out['max_behind_s']} s)")  # fmt: skip
    print(f"serve: {out['serve_estimates']} estimates, exit {out['serve_exit']}, "
          f"rejected {out['rejected']}, received all: {out['serve_received_all']}")  # fmt: skip
    print(f"transport: {out['transport']}")
    print(f"{'robot':8} {'poses':>6} {'APE median m':>13} {'n':>6}")
    for robot, n in out["poses_received"].items():
        print(f"{robot:8} {n:6d} {out['ape_median_m'].get(robot, float('nan')):13.4f} "
              f"{out['ape_n'].get(robot, 0):6d}")  # fmt: skip
    print(f"pose frames {out['pose_frames']}; status messages {out['status_messages']}; "
          f"git clones attempted {len(out['clone_attempts'])}")  # fmt: skip
    for topic, info in out["endpoints"].items():
        print(f"{topic}: {info}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
