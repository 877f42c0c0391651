"""``relloc serve`` and ``relloc replay``: the command-line faces of the live engine."""

from __future__ import annotations

import argparse
import gc
import json
from pathlib import Path
from typing import Any

from relloc.cli import argtypes
from relloc.cli.common import (
    UserError,
    add_zenoh_args,
    check_writable,
    counting_refusals,
    format_stamp,
    interface_from_args,
    open_command_session,
    options_from_args,
    session_security,
    stop_on_signals,
)
from relloc.config import TeamConfig
from relloc.faults import Faults
from relloc.faults import add_arguments as add_fault_arguments
from relloc.faults import from_args as faults_from_args
from relloc.live.publish import ReplayOptions, replay_bag
from relloc.live.server import LiveServer, ServeOptions
from relloc.runs.rejections import rejection_lines
from relloc.sources.table import source_kind

__all__ = ["register"]


def _cmd_serve(args: argparse.Namespace) -> int:
    from relloc.methods import parse_methods

    config = TeamConfig.load(args.config)
    if args.record is not None:
        check_writable(args.record.parent, "--record")
    if args.foxglove is not None:
        _check_foxglove(args.foxglove)
    elif args.ground_truth:
        raise UserError("--ground-truth feeds the viewer only: give --foxglove too")
    opts = options_from_args(
        ServeOptions,
        args,
        methods=tuple(parse_methods(args.methods)),
        interface=interface_from_args(args, config),
        faults=_faults(args),
    )
    security = session_security(args)
    with counting_refusals(security) as refusals:
        summary = _serve(config, opts, args, security.describe())
    _print_summary(summary)
    if refusals is not None:
        summary["access_refused"] = refusals.as_dict()
        for line in refusals.lines():
            print(f"  {line}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(summary, indent=2))
    return 0


def _check_foxglove(address: str) -> None:
    """``--foxglove`` names an address and the viewer extra is installed (else a clear error)."""
    from relloc.sinks.foxglove import parse_address, require_sdk

    try:
        parse_address(address)
        require_sdk()
    except (ValueError, ImportError) as exc:
        raise UserError(str(exc)) from None


def _serve(
    config: TeamConfig, opts: ServeOptions, args: argparse.Namespace, security: str
) -> dict[str, Any]:
    session = open_command_session(args)
    try:
        server = LiveServer(config, session, opts)
    except Exception:
        session.close()
        raise
    _freeze_startup_objects()
    try:
        with stop_on_signals(server.stop):
            server.start()
            print(
                f"relloc serve: {config.name}, {', '.join(opts.methods)}, "
                f"{server.config.filter.particles} particles; {opts.interface.kind} interface, "
                f"{len(server.source.keys)} topics in, "
                f"estimates on {server.sink.key('<robot>', opts.methods[0])}",
                flush=True,
            )
            print(f"  zenoh session {security}", flush=True)
            viewer = server.viewer
            if viewer is not None:
                print(f"  foxglove viewer on ws://{viewer.host}:{viewer.port}", flush=True)
            return server.run(args.duration)
    finally:
        server.close()
        session.close()


def _freeze_startup_objects() -> None:
    """Move every object alive after start-up (modules, type store, filter) out of the cyclic
    garbage collector's sight: a full collection otherwise walks them all (about 80 000
    objects, some 0.1 s) now and then, in the middle of a filter step. Changes no result."""
    gc.collect()
    gc.freeze()


def _faults(args: argparse.Namespace) -> Faults:
    try:
        return faults_from_args(args)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def _print_summary(s: dict[str, Any]) -> None:
    src = s["source"]
    print(f"stopped after {s['uptime_s']:.1f} s: {src['messages']} messages, {s['events']} events")
    print(f"  out of order (passed on): {src['out_of_order']}")
    for line in rejection_lines("source", src["rejected"]) or ["source dropped nothing"]:
        print(f"  {line}")
    for name, m in s["methods"].items():
        print(
            f"  {name}: {m['estimates']} estimates, last {format_stamp(m['last_estimate_t'])}, "
            f"ESS {m['ess']}, compute {m['compute_s']:.2f} s"
        )
        for line in rejection_lines(name, m["rejected"]):
            print(f"    {line}")
    if s["engine_errors"]:
        print(f"  engine errors: {s['engine_errors']} (see the log)")
    if "record" in s:
        print(f"  recorded {s['record']['messages']} messages to {s['record']['path']}")


def _cmd_replay(args: argparse.Namespace) -> int:
    kind = source_kind(args.bag)
    if not kind.replayable:
        raise UserError(
            f"{args.bag} is {kind.what}: relloc replay publishes the ROS 2 messages of a rosbag2 recording"
        )
    config = TeamConfig.load(args.config)
    opts = options_from_args(
        ReplayOptions, args, interface=interface_from_args(args, config), faults=_faults(args)
    )
    session = open_command_session(args)
    try:
        with stop_on_signals() as stop:
            stats = replay_bag(Path(args.bag), config, session, opts, stop=stop.is_set)
    finally:
        session.close()
    d = stats.as_dict()
    print(
        f"replayed {d['messages']} messages on {d['keys']} keys in {d['wall_s']:.1f} s "
        f"(rate {opts.rate:g}, at worst {1e3 * stats.max_behind_s:.1f} ms behind schedule)"
    )
    if stats.unmatched:
        print(f"  no subscriber when it started: {', '.join(stats.unmatched)}")
    if stats.injected:
        print(
            "  faults injected: " + ", ".join(f"{k} {v}" for k, v in sorted(stats.injected.items()))
        )
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``serve`` and ``replay`` to the ``relloc`` command line."""
    serve = sub.add_parser(
        "serve",
        help="run the localizer live on Zenoh (ROS 2 via zenoh-bridge-ros2dds or rmw_zenoh)",
        description="Subscribe to the team's odometry and UWB (and detection) topics on Zenoh, as "
        "zenoh-bridge-ros2dds publishes them or as robots on rmw_zenoh do (--ros-interface), run the "
        "localizer on them live and publish each robot's pose relative to the reference on "
        "<out-prefix>/<robot>/pose and a JSON status. Ctrl-C or SIGTERM stops it and prints its "
        "figures (docs/explanation/live-engine.md).",
    )
    serve.add_argument("--config", required=True, help="team config (TOML)")
    serve.add_argument(
        "--methods",
        default="pf",
        help="comma-separated; the first one is published on relloc/<robot>/pose",
    )
    serve.add_argument("--seed", type=argtypes.seed, default=0, help="random seed of the filter")
    add_fault_arguments(serve)
    serve.add_argument(
        "--particles",
        type=argtypes.count,
        default=None,
        help="override the config's particle count",
    )
    serve.add_argument(
        "--models", type=Path, default=None, help="trained range-error models (for pf_ul)"
    )
    serve.add_argument(
        "--out-prefix", default="relloc", help="key prefix of the estimates and status"
    )
    serve.add_argument(
        "--robot",
        default="",
        metavar="NAME",
        help="run on board robot NAME: the team relative to it, in its body frame, on "
        "<out-prefix>/NAME/<other>/pose and <out-prefix>/NAME/status (the config's reference "
        "replaced by NAME)",
    )
    serve.add_argument("--reorder-window", type=argtypes.non_negative, default=0.0, metavar="S",
                       help="hold events up to S s of header time to put them in order (adds S s of latency)")  # fmt: skip
    serve.add_argument("--clock-rate", type=argtypes.positive, default=1.0,
                       help="header seconds per wall second (match relloc replay --rate)")  # fmt: skip
    serve.add_argument("--status-period", type=argtypes.positive, default=1.0, metavar="S",
                       help="seconds between two status messages")  # fmt: skip
    serve.add_argument(
        "--trace",
        action="store_true",
        help="publish a latency trace per estimate on <out-prefix>/trace",
    )
    serve.add_argument(
        "--subscribe-all",
        action="store_true",
        help="subscribe to <prefix>/** (unknown keys are counted)",
    )
    serve.add_argument(
        "--duration", type=argtypes.positive, default=None, metavar="S", help="stop after S seconds"
    )
    serve.add_argument(
        "--json", default=None, metavar="FILE", help="write the final figures as JSON"
    )
    serve.add_argument(
        "--record", type=Path, default=None, metavar="FILE",
        help="write every estimate published, its flags and the ranges used to the MCAP file "
        "FILE (as relloc run --mcap, without truth), finished when serve stops",
    )  # fmt: skip
    serve.add_argument(
        "--foxglove", default=None, metavar="[HOST:]PORT",
        help="also serve the team to Foxglove over WebSocket on HOST:PORT (HOST 127.0.0.1 unless "
        "given; 0.0.0.0: every interface): poses, scene, flags, status (needs relloc[viewer])",
    )  # fmt: skip
    serve.add_argument(
        "--foxglove-rate", type=argtypes.positive, default=10.0, metavar="HZ",
        help="at most HZ messages a second on each Foxglove channel (default 10)",
    )  # fmt: skip
    serve.add_argument(
        "--ground-truth", action="store_true",
        help="also subscribe to the robots' motion capture (mocap_topic, as relloc replay "
        "--ground-truth publishes it): the viewer's truth poses and errors, never the filter's",
    )  # fmt: skip
    serve.add_argument(
        "--compiled", action=argparse.BooleanOptionalAction, default=None,
        help="run the particle filter's step compiled (numba: less CPU, about 130 MB more "
        "memory) or as NumPy (--no-compiled); default NumPy, RELLOC_COMPILED=1 compiled "
        "(docs/howto/live-robots.md)",
    )  # fmt: skip
    add_zenoh_args(serve, "serve")
    serve.set_defaults(handler=_cmd_serve)

    replay = sub.add_parser(
        "replay",
        help="publish a rosbag2 recording on Zenoh as the robots would",
        description="Publish a rosbag2 recording's topics on Zenoh as CDR, on the keys the robots "
        "behind zenoh-bridge-ros2dds would use, in real time (or --rate times faster).",
    )
    replay.add_argument("bag", help="bag folder (metadata.yaml) or .db3/.mcap file")
    replay.add_argument(
        "--config", required=True, help="team config (TOML): keys of the team's topics"
    )
    replay.add_argument(
        "--rate", type=argtypes.positive, default=1.0, help="speed factor (2: twice as fast)"
    )
    replay.add_argument("--team-only", action="store_true", help="publish only the team's topics")
    replay.add_argument(
        "--ground-truth", action="store_true", help="also publish motion capture (mocap_topic)"
    )
    replay.add_argument(
        "--wait",
        type=float,
        default=10.0,
        metavar="S",
        help="wait up to S s for the server's subscribers",
    )
    replay.add_argument("--start", type=float, default=0.0, metavar="S", help="skip S s of the bag")
    replay.add_argument(
        "--duration", type=argtypes.positive, default=None, metavar="S", help="publish only S s"
    )
    add_fault_arguments(replay)
    add_zenoh_args(replay, "team")
    replay.set_defaults(handler=_cmd_replay)
