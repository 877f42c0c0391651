"""``relloc navigate`` and ``relloc sim-robots``: the live navigation commands.

Thin layers over :mod:`relloc.navigation.live`: parse arguments, open a Zenoh session (the same
options as ``relloc serve``), run until done or Ctrl-C/SIGTERM, print a summary (``--json`` for
scripts). Expected failures (bad config, bad path file, unknown robot) are one line, exit 2.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

from relloc.cli import argtypes
from relloc.cli.common import (
    UserError,
    add_zenoh_args,
    counting_refusals,
    interface_from_args,
    open_command_session,
    options_from_args,
    session_security,
    stop_on_signals,
)

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``navigate`` and ``sim-robots`` to the ``relloc`` command line."""

    nav = sub.add_parser(
        "navigate",
        help="drive a robot along a path using the relative estimate (publishes cmd_vel on Zenoh)",
        description=(
            "Follow a waypoint path given relative to the reference robot, with the localizer's "
            "estimate as position feedback and the robot's odometry as heading; publishes "
            "geometry_msgs/Twist on the robot's cmd_vel key. Zero velocity when the estimate is "
            "stale or uncertain, on Ctrl-C and at the end of the path."
        ),
    )
    nav.add_argument("--config", required=True, help="team config (TOML)")
    nav.add_argument("--robot", required=True, help="the robot to drive (not the reference)")
    nav.add_argument(
        "--path", required=True, help="path file (TOML), e.g. configs/paths/rectangle.toml"
    )
    g = nav.add_argument_group("controller (overrides the path file's [controller])")
    g.add_argument(
        "--rate", type=float, default=None, metavar="HZ", help="control rate (default 10)"
    )
    g.add_argument(
        "--max-v", type=float, default=None, metavar="M/S", help="speed limit (default 0.25)"
    )
    g.add_argument(
        "--max-w", type=float, default=None, metavar="RAD/S", help="turn-rate limit (default 1.0)"
    )
    g.add_argument(
        "--lookahead",
        type=float,
        default=None,
        metavar="M",
        help="pure-pursuit lookahead (default 0.4)",
    )
    g.add_argument("--goal-tolerance", type=float, default=None, metavar="M", help="default 0.08")
    s = nav.add_argument_group("safety (overrides the path file's [safety])")
    s.add_argument(
        "--max-age",
        type=float,
        default=None,
        metavar="S",
        help="stale estimate/odometry age (default 0.6)",
    )
    s.add_argument(
        "--max-std",
        type=float,
        default=None,
        metavar="M",
        help="largest position std (default 0.2)",
    )
    s.add_argument(
        "--start-std",
        type=float,
        default=None,
        metavar="M",
        help="largest position std at which a held robot starts (default 0.15)",
    )
    s.add_argument(
        "--settle-time",
        type=float,
        default=None,
        metavar="S",
        help="checks must pass this long before moving (default 2)",
    )
    e = nav.add_argument_group("estimate")
    e.add_argument(
        "--in-process",
        action="store_true",
        help="run the localizer here instead of using relloc serve",
    )
    e.add_argument(
        "--estimate-prefix",
        default="relloc",
        help="key prefix of serve's estimates (its --out-prefix)",
    )
    e.add_argument(
        "--methods", default="pf", help="with --in-process: the methods (the first drives)"
    )
    e.add_argument(
        "--particles",
        type=argtypes.count,
        default=None,
        help="with --in-process: override the particle count",
    )
    e.add_argument("--seed", type=argtypes.seed, default=0, help="with --in-process")
    e.add_argument(
        "--reorder-window",
        type=argtypes.non_negative,
        default=0.1,
        metavar="S",
        help="with --in-process: fuse events in stamp order within S s (default 0.1; serve's "
        "--reorder-window)",
    )
    e.add_argument(
        "--clock-rate",
        type=argtypes.positive,
        default=1.0,
        help="data seconds per wall second (sim-robots --rate)",
    )
    e.add_argument(
        "--no-latency-compensation",
        dest="latency_compensation",
        action="store_false",
        help="use the estimate as is, not moved forward by odometry to the control time",
    )
    nav.add_argument(
        "--duration",
        type=argtypes.positive,
        default=None,
        metavar="S",
        help="stop (zero velocity) after S s",
    )
    nav.add_argument("--json", default=None, metavar="FILE", help="write the summary as JSON")
    add_zenoh_args(nav, "navigate")
    nav.set_defaults(handler=_cmd_navigate)

    sim = sub.add_parser(
        "sim-robots",
        help="a simulated team on Zenoh: publishes odometry and UWB like real robots, obeys cmd_vel",
        description=(
            "Run a simulated team in real time and publish its odometry (nav_msgs/Odometry), UWB "
            "ranges (sensor_msgs/Range) and motion capture as CDR on the keys real robots behind "
            "zenoh-bridge-ros2dds (or, with --ros-interface rmw_zenoh, rmw_zenoh) would use; "
            "commanded robots follow geometry_msgs/Twist on their "
            "cmd_vel key. With relloc serve and relloc navigate: the whole live system on one machine."
        ),
    )
    sim.add_argument(
        "--scenario",
        choices=("nav", "multi", "single"),
        default="nav",
        help="nav: the multi team with --robot driven by cmd_vel (default)",
    )
    sim.add_argument(
        "--config",
        default=None,
        help="a team config naming the scenario's robots: its topics, scopes and filter are used",
    )
    sim.add_argument(
        "--robot", default=None, help="the commanded robot (nav: r2; other scenarios: none)"
    )
    sim.add_argument("--seed", type=argtypes.seed, default=0, help="random seed of the simulation")
    sim.add_argument(
        "--rate", type=argtypes.positive, default=1.0, help="simulated seconds per wall second"
    )
    sim.add_argument(
        "--duration", type=argtypes.positive, default=600.0, metavar="S", help="simulated seconds"
    )
    sim.add_argument(
        "--write-config",
        default=None,
        metavar="FILE",
        help="write the team config for relloc serve/navigate (first thing it does)",
    )
    sim.add_argument("--config-only", action="store_true", help="write --write-config and exit")
    sim.add_argument(
        "--particles",
        type=argtypes.count,
        default=None,
        help="particle count written into the config",
    )
    sim.add_argument(
        "--cmd-timeout",
        type=float,
        default=0.5,
        metavar="S",
        help="a commanded robot stops after S simulated seconds without cmd_vel",
    )
    sim.add_argument(
        "--no-ground-truth",
        dest="ground_truth",
        action="store_false",
        help="do not publish motion capture",
    )
    sim.add_argument(
        "--wait",
        type=float,
        default=30.0,
        metavar="S",
        help="wait up to S s for a subscriber (relloc serve) before starting",
    )
    sim.add_argument(
        "--json", default=None, metavar="FILE", help="write the summary and true trajectories"
    )
    add_zenoh_args(sim, "team")
    sim.set_defaults(handler=_cmd_sim_robots)


def _overrides(args: argparse.Namespace, names: dict[str, str]) -> dict[str, Any]:
    return {
        key: getattr(args, attr) for attr, key in names.items() if getattr(args, attr) is not None
    }


def _cmd_navigate(args: argparse.Namespace) -> int:
    from relloc.config import TeamConfig
    from relloc.live.secure.access import SERVE
    from relloc.methods import parse_methods
    from relloc.navigation.controller import ControllerConfig
    from relloc.navigation.live import NavigateOptions
    from relloc.navigation.path import load_path
    from relloc.navigation.safety import SafetyConfig

    config = TeamConfig.load(args.config)
    path = load_path(args.path)
    if args.robot not in config.robot_names:
        raise UserError(
            f"unknown robot {args.robot!r}; the team is {', '.join(config.robot_names)}"
        )
    if args.robot == config.reference:
        raise UserError(
            f"{args.robot} is the reference robot (always at (0, 0) in the relative frame); "
            "navigate another robot"
        )
    if path.reference and path.reference != config.reference:
        raise UserError(
            f"path {path.name!r} is relative to {path.reference!r}, but the team's reference "
            f"robot is {config.reference!r}"
        )
    controller = ControllerConfig().updated(path.controller, "path.controller")
    controller = controller.updated(
        _overrides(
            args,
            {
                "rate": "rate_hz",
                "max_v": "max_v",
                "max_w": "max_w",
                "lookahead": "lookahead",
                "goal_tolerance": "goal_tolerance",
            },
        ),
        "options",
    )
    safety = SafetyConfig().updated(path.safety, "path.safety")
    safety = safety.updated(
        _overrides(
            args,
            {
                "max_age": "max_age",
                "max_std": "max_std",
                "start_std": "start_std",
                "settle_time": "settle_time",
            },
        ),
        "options",
    )
    opts = options_from_args(
        NavigateOptions,
        args,
        path=path,
        controller=controller,
        safety=safety,
        methods=tuple(parse_methods(args.methods)),
        interface=interface_from_args(args, config),
        pose_identity=SERVE if args.secure and not args.in_process else None,
    )
    security = session_security(args)
    with counting_refusals(security) as refusals:
        summary = _navigate(config, opts, args, security.describe())
    if refusals is not None:
        summary["access_refused"] = refusals.as_dict()
    t0 = summary["t0"] or 0.0
    for rec in summary["stops"]:
        verb = "stop" if rec["stop"] else "go  "
        print(f"  {verb} at {rec['t'] - t0:6.2f} s: {rec['reason']} ({rec['detail']})")
    print(
        f"ended: {summary['ended']}; path {'completed' if summary['completed'] else 'not completed'}; "
        f"{summary['received']['estimate']} estimates and {summary['received']['odometry']} "
        f"odometry messages received, {summary['commands_sent']} commands sent"
    )
    if summary["received"]["unverified"]:
        print(f"  estimates not used (publisher not verified): {summary['received']['unverified']}")
    if refusals is not None:
        for line in refusals.lines():
            print(f"  {line}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(summary, indent=2))
    if summary["ended"] == "interrupted":
        return 130
    return 0 if summary["completed"] or summary["ended"] == "duration" else 1


def _navigate(config: Any, opts: Any, args: argparse.Namespace, security: str) -> dict[str, Any]:
    from relloc.navigation.live import LiveNavigation

    path = opts.path
    session = open_command_session(args)
    try:
        try:
            live = LiveNavigation(config, session, opts)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        source = "in-process localizer" if args.in_process else live.pose_key
        print(
            f"relloc navigate: {args.robot} along {path.name!r} ({path.length:.1f} m, "
            f"{len(path.waypoints)} waypoints) relative to {config.reference}; estimate from "
            f"{source}, odometry on {live.odom_key}, commands on {live.cmd_key}",
            flush=True,
        )
        trusted = f"; poses only from {opts.pose_identity!r}" if opts.pose_identity else ""
        print(f"  zenoh session {security}{trusted}", flush=True)
        with stop_on_signals() as stop:
            live.start()
            try:
                return live.run(stop)
            finally:
                live.close()
    finally:
        session.close()


def _cmd_sim_robots(args: argparse.Namespace) -> int:
    from relloc.config import TeamConfig
    from relloc.live.sim_robots import SimRobots, SimRobotsOptions, sim_team_config
    from relloc.simulator import multi_scenario, nav_scenario, single_scenario

    robot = args.robot or ("r2" if args.scenario == "nav" else None)
    commanded = (robot,) if robot else ()
    try:
        if args.scenario == "nav":
            sim = nav_scenario(args.seed, robot=robot or "r2", duration=args.duration)
        elif args.scenario == "multi":
            sim = multi_scenario(args.seed, duration=args.duration, commanded=commanded)
        else:
            sim = single_scenario(args.seed, duration=args.duration, commanded=commanded)
        base = TeamConfig.load(args.config) if args.config else None
        config = sim_team_config(sim, base, args.particles)
    except ValueError as exc:
        if type(exc) is not ValueError:
            raise
        raise UserError(str(exc)) from None
    interface = interface_from_args(args, config)
    # the config a server of this team needs: the interface and distribution it was given
    config = replace(config, ros_interface=interface.kind, ros_distro=interface.distro)
    if args.write_config:
        Path(args.write_config).parent.mkdir(parents=True, exist_ok=True)
        config.save(args.write_config)
        print(f"team config written to {args.write_config}", flush=True)
    if args.config_only:
        if not args.write_config:
            raise UserError("--config-only needs --write-config FILE")
        return 0
    opts = options_from_args(SimRobotsOptions, args, interface=interface)
    session = open_command_session(args)
    try:
        robots = SimRobots(sim, config, session, opts)
        print(
            f"relloc sim-robots: {args.scenario} (seed {args.seed}), {len(sim.robots)} robots, "
            f"{len(robots.odom_keys)} odometry and {len(robots.range_keys)} range keys, "
            f"commands on {', '.join(robots.cmd_keys.values()) or 'none'}; x{args.rate:g} real time",
            flush=True,
        )
        with stop_on_signals() as stop:
            robots.start()
            try:
                summary = robots.run(stop)
            finally:
                robots.close()
    finally:
        session.close()
    print(
        f"stopped after {summary['simulated_s']:.1f} simulated s: {summary['messages']} messages "
        f"published, {summary['commands_received']} commands received"
    )
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(summary, indent=1))
    return 0
