"""Command line: ``relloc demo | run | calibrate | ranging | serve | replay | navigate | ...``.

The whole command-line layer lives in this package, on top of the library; nothing below
imports it. This module is the parser and the dispatch; each command family registers itself
from its own module (:mod:`.live`, :mod:`.navigation`, :mod:`.ranging`);
:mod:`.common` holds what they share (user errors, signals, Zenoh sessions, options from
arguments). Each command is a thin layer: parse arguments, call one function of the
library (``demo`` and ``run``: :mod:`relloc.runs`), print.
Expected failures (bad config, unreadable bag, unknown method) print one clear line and exit
with status 2; they never show a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from relloc import __version__
from relloc.cli import argtypes
from relloc.cli.common import UserError, check_writable, is_user_error, options_from_args
from relloc.faults import add_arguments as add_fault_arguments
from relloc.malloc import tune_malloc

_COMMAND_MODULES = (
    "relloc.cli.ranging",
    "relloc.cli.live",
    "relloc.cli.navigation",
    "relloc.cli.secure",
    "relloc.cli.init",
)
"""Command families with a ``register(subparsers)`` of their own. None imports an optional
dependency at module level (training imports torch only when it runs), so every command is
always listed; a module that fails to import is a bug and raises."""


METHODS_HELP = (
    "comma-separated methods: pf (particle filter: odometry + UWB ranges), "
    "pf_ul (pf on learned-corrected ranges, needs --models), pf_uv (pf + cooperative detections), "
    "pf_ulv (both), multilateration (least squares on each step's ranges), "
    "ekf_oracle (centralised EKF over all poses started at the ground truth: MRCLAM data sets)"
)


def _check_outputs(args: argparse.Namespace) -> None:
    """--out and --json must be writable before a run of minutes starts."""
    if getattr(args, "out", None) is not None:
        check_writable(args.out)
    if getattr(args, "json_path", None) is not None:
        check_writable(args.json_path.parent or Path("."), "--json")
    if getattr(args, "mcap", None) is not None:
        check_writable(args.mcap.parent or Path("."), "--mcap")


def _cmd_demo(args: argparse.Namespace) -> int:
    from relloc.methods import parse_methods
    from relloc.runs.demo import SCENARIOS, DemoOptions, run_demo

    known = [*SCENARIOS, "nav"]
    for name in args.scenarios.split(","):
        if name not in known:
            raise UserError(f"unknown scenario {name!r}; known: {', '.join(known)}")
    if "grid" in args.scenarios.split(",") and args.robots < 2:
        raise UserError(f"--robots: the grid needs at least 2 robots, got {args.robots}")
    opts = options_from_args(
        DemoOptions,
        args,
        methods=tuple(parse_methods(args.methods)),
        scenarios=tuple(args.scenarios.split(",")),
        faults=_faults(args),
    )
    _check_outputs(args)
    run_demo(opts)
    return 0


def _faults(args: argparse.Namespace) -> Any:
    from relloc import faults

    try:
        return faults.from_args(args)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def _cmd_run(args: argparse.Namespace) -> int:
    from relloc.config import TeamConfig
    from relloc.methods import parse_methods
    from relloc.runs.recording import RunOptions, run_recording
    from relloc.sources.rosbag import recording_name

    config = TeamConfig.load(args.config) if args.config else None
    if args.out is None:
        args.out = Path("out") / recording_name(args.bag)
    opts = options_from_args(
        RunOptions, args, methods=tuple(parse_methods(args.methods)), faults=_faults(args)
    )
    _check_outputs(args)
    run_recording(Path(args.bag), config, opts)
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    import json

    from relloc.config import TeamConfig
    from relloc.drafting.calibrate import calibrate, calibration_section, edit_config_text

    config = TeamConfig.load(args.config)
    text = Path(args.config).read_text()
    node_map = None
    if args.node_map:
        try:
            node_map = {
                int(k): v for k, v in (item.split("=") for item in args.node_map.split(","))
            }
        except ValueError:
            raise UserError(
                f"--node-map must look like 1=n_7,3=n_3, got {args.node_map!r}"
            ) from None
    out = Path(args.config) if args.in_place else (Path(args.write) if args.write else None)
    if out is not None:
        check_writable(out.parent, "--write" if args.write else "--in-place")
    cal = calibrate(
        Path(args.source),
        config,
        node_map=node_map,
        headings=args.headings,
        fit_scale=args.scale,
        span=args.span,
    )
    if out is None:
        sys.stdout.write(calibration_section(cal, text))
        print(
            f"relloc calibrate: nothing written; --in-place writes this into {args.config}, "
            "--write FILE writes a calibrated copy to FILE (comments kept)",
            file=sys.stderr,
        )
        return 0
    out.write_text(edit_config_text(text, cal))
    print(json.dumps(cal.summary(), indent=2))
    print(f"calibration from {args.source} written to {out}")
    return 0


class _HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter, adding ``(default: X)`` to an option's help where the text does
    not already say its default and the default is a value (not None, False or a flag's)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if (
            "default" in text.lower()
            or any(default is v for v in (None, False, True, argparse.SUPPRESS))
            or default == []
            or not action.option_strings
        ):
            return text
        return f"{text} (default: %(default)s)"


def _every_parser(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """``parser`` and every (nested) subcommand parser below it."""
    out = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                out += _every_parser(sub)
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="relloc",
        description="Relative multi-robot localization: odometry + UWB ranges + cooperative detections. "
        "Run the commands from the repository root (configs/ and out/ are relative paths).",
        epilog="relloc with no command prints this help (exit status 0). Errors print one line "
        "'relloc <command>: error: ...' and exit with status 2.",
    )
    parser.add_argument("--version", action="version", version=f"relloc {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log warnings and details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    demo = sub.add_parser(
        "demo",
        help="run the simulated scenarios with every method",
        description="Run the simulated scenarios of the paper (multi: five robots; single: two "
        "robots, one range; nav: closed-loop navigation on the estimate) through the engine, print "
        "APE per method and robot, and write plots and JSON. Needs no data and no PyTorch.",
    )
    demo.add_argument(
        "--seed", type=argtypes.seed, default=0, help="seed of the simulation and the filters"
    )
    demo.add_argument(
        "--warmup", type=argtypes.non_negative, default=10.0, help="seconds excluded from APE"
    )
    demo.add_argument(
        "--particles", type=argtypes.count, default=None, help="override the particle count"
    )
    demo.add_argument("--methods", default="pf,multilateration", help=METHODS_HELP)
    demo.add_argument(
        "--scenarios",
        default="multi,single,nav",
        help="comma-separated: multi, single, nav, static, static_then_move, grid (the scaling scenario: --robots N on a grid, all pairs ranging), tags and tags_odometry (two UWB tags a robot, without and with odometry), drones and drones_uwb (five quadrotors in 3D, two tags each, with velocity odometry and heights, and with UWB only)",
    )
    demo.add_argument(
        "--robots",
        type=argtypes.count,
        default=5,
        help="team size of the grid scenario (at least 2)",
    )
    demo.add_argument("--out", type=Path, default=Path("out/demo"), help="folder for plots")
    demo.add_argument(
        "--json",
        dest="json_path",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the figures as JSON",
    )
    demo.add_argument(
        "--no-progress", dest="progress", action="store_false", help="no progress bar"
    )
    add_fault_arguments(demo)
    _add_mode_flags(demo)
    _add_filter_kind(demo)
    demo.set_defaults(handler=_cmd_demo)

    run = sub.add_parser(
        "run",
        help="run methods over a rosbag2 recording (an MRCLAM data set folder, a simulated scenario) and evaluate them",
        description="Stream a rosbag2 recording (an MRCLAM data set, or a simulated scenario) through "
        "each method, evaluate against its motion capture, print APE per method and robot, and "
        "write plots and TUM trajectories to out/<recording>/ (or --out). The filter never sees "
        "the motion capture.",
    )
    run.add_argument(
        "bag",
        help="bag folder (metadata.yaml) or .db3/.mcap file, an MRCLAM data set folder, or a scenario name (multi, single, ...)",
    )
    run.add_argument(
        "--config",
        default=None,
        help="team config (TOML), e.g. configs/tiers/...; required but for a simulated scenario, which brings its own",
    )
    run.add_argument("--methods", default="pf,multilateration", help=METHODS_HELP)
    run.add_argument("--seed", type=argtypes.seed, default=0, help="seed of the filters")
    run.add_argument(
        "--warmup", type=argtypes.non_negative, default=5.0, help="seconds excluded from APE"
    )
    run.add_argument(
        "--particles",
        type=argtypes.count,
        default=None,
        help="override the config's particle count",
    )
    run.add_argument(
        "--models", type=Path, default=None, help="trained range-error models (for pf_ul)"
    )
    run.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder for plots and TUM trajectories (default: out/<recording>/)",
    )
    run.add_argument(
        "--json",
        dest="json_path",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the figures as JSON",
    )
    run.add_argument(
        "--mcap",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the estimates, their flags, the truth and the ranges as ROS 2 messages to an MCAP file (Foxglove, RViz)",
    )
    run.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    add_fault_arguments(run)
    _add_mode_flags(run)
    run.add_argument(
        "--reference",
        default=None,
        metavar="ROBOT",
        help="another reference robot (default: the config's reference)",
    )
    _add_filter_kind(run)
    run.add_argument(
        "--span",
        type=argtypes.span,
        default=None,
        metavar="START:END",
        help="only the events between these seconds from the recording's start (either may be left out)",
    )
    run.add_argument(
        "--sightings",
        choices=("both", "range", "bearing"),
        default="both",
        help="what of each teammate sighting to fuse (MRCLAM data sets): range and bearing, or one of them",
    )
    run.set_defaults(handler=_cmd_run)

    cal = sub.add_parser(
        "calibrate",
        help="estimate UWB pair biases (and heading offsets) for a config",
        description="Estimate UWB node-pair biases (and optionally heading offsets) from a "
        "recording with motion capture or a CSV of UWB errors. Writes nothing unless asked: "
        "without --in-place or --write it prints the calibrated TOML section. Writing keeps the "
        "config's comments and never adds per-pair sigmas the config leaves unset.",
    )
    cal.add_argument("source", help="a bag with motion capture, or a CSV of UWB errors")
    cal.add_argument("--config", required=True, help="the team config to calibrate (TOML)")
    where = cal.add_mutually_exclusive_group()
    where.add_argument(
        "--in-place", action="store_true", help="rewrite --config with the calibration"
    )
    where.add_argument(
        "--write", default=None, metavar="FILE", help="write a calibrated copy of --config to FILE"
    )
    cal.add_argument(
        "--node-map",
        default=None,
        help="CSV robot numbers to nodes, e.g. 1=n_7,3=n_3 (default: the TIERS map)",
    )
    cal.add_argument(
        "--headings", action="store_true", help="also heading offsets from the first mocap pose"
    )
    cal.add_argument("--scale", action="store_true", help="also fit a range scale per pair")
    cal.add_argument(
        "--span",
        type=argtypes.span,
        default=None,
        metavar="START:END",
        help="only the events between these seconds from the recording's start (either may be left out)",
    )
    cal.set_defaults(handler=_cmd_calibrate)

    _register_optional(sub)
    for p in _every_parser(parser):
        p.formatter_class = _HelpFormatter
    return parser


def _add_filter_kind(parser: argparse.ArgumentParser) -> None:
    """``--filter-kind``: a registered kind or ``auto`` (:mod:`relloc.estimators`)."""
    from relloc import estimators

    parser.add_argument(
        "--filter-kind",
        default=None,
        choices=estimators.names(),
        help="the filter the pf methods run (default: the config's [filter] kind)",
    )


def _add_mode_flags(parser: argparse.ArgumentParser) -> None:
    """Self-calibration modes (docs/explanation/self-calibration.md); the default is the config's."""
    from relloc.config import FilterConfig

    parser.add_argument(
        "--heading",
        choices=FilterConfig.choices("heading_mode"),
        default=None,
        help="compass: heading offsets from the config; estimate: estimated online (default: the config's [filter] heading_mode)",
    )
    parser.add_argument(
        "--bias",
        choices=FilterConfig.choices("bias_mode"),
        default=None,
        help="UWB pair biases from the config (calibrated) or estimated online (default: the config's bias_mode)",
    )
    parser.add_argument(
        "--odom-scale",
        choices=FilterConfig.choices("odom_scale_mode"),
        default=None,
        help="odometry scales from the config (fixed) or estimated online (default: the config's odom_scale_mode)",
    )


def _register_optional(sub: argparse._SubParsersAction) -> None:
    """Commands that live in their own modules register themselves here."""
    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(sub)


def main(argv: Sequence[str] | None = None) -> int:
    tune_malloc()  # freed filter temporaries stay mapped: no page faults per step (relloc.malloc)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.ERROR,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # expected user errors become one line
        if is_user_error(exc):
            print(f"relloc {args.command}: error: {exc}", file=sys.stderr)
            return 2
        raise
