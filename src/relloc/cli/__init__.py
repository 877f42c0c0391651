"""Command line: ``relloc demo | run | calibrate | ranging | serve | replay | navigate | ...``.

The whole command-line layer lives in this package, on top of the library; nothing below
imports it. This module is the parser and the dispatch; each command family registers itself
from its own module (:mod:`.live`, :mod:`.navigation`, :mod:`.ranging`, :mod:`.bench_resources`);
:mod:`.common` holds what they share (user errors, signals, Zenoh sessions, options from
arguments). Each command is a thin layer: parse arguments, call one function, print.
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

from relloc import __version__
from relloc.cli import argtypes
from relloc.cli.common import UserError, is_user_error, options_from_args

_COMMAND_MODULES = ("relloc.cli.ranging", "relloc.cli.live", "relloc.cli.bench_resources", "relloc.cli.navigation")
"""Command families with a ``register(subparsers)`` of their own. None imports an optional
dependency at module level (training imports torch only when it runs), so every command is
always listed; a module that fails to import is a bug and raises."""


def _cmd_demo(args: argparse.Namespace) -> int:
    from relloc.cli.demo import SCENARIOS, DemoOptions, run_demo
    from relloc.methods import parse_methods

    known = [*SCENARIOS, "nav"]
    for name in args.scenarios.split(","):
        if name not in known:
            raise UserError(f"unknown scenario {name!r}; known: {', '.join(known)}")
    opts = options_from_args(
        DemoOptions, args, methods=tuple(parse_methods(args.methods)), scenarios=tuple(args.scenarios.split(","))
    )
    run_demo(opts)
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from relloc.cli.recording import RunOptions, run_recording
    from relloc.config import TeamConfig
    from relloc.methods import parse_methods

    config = TeamConfig.load(args.config)
    opts = options_from_args(RunOptions, args, methods=tuple(parse_methods(args.methods)))
    run_recording(Path(args.bag), config, opts)
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    import json

    from relloc.cli.recording import calibrate
    from relloc.config import TeamConfig

    config = TeamConfig.load(args.config)
    node_map = None
    if args.node_map:
        try:
            node_map = {int(k): v for k, v in (item.split("=") for item in args.node_map.split(","))}
        except ValueError:
            raise UserError(f"--node-map must look like 1=n_7,3=n_3, got {args.node_map!r}") from None
    new, summary = calibrate(Path(args.source), config, node_map=node_map, headings=args.headings, fit_scale=args.scale)
    out = Path(args.write or args.config)
    new.save(out)
    print(json.dumps(summary, indent=2))
    print(f"calibration from {args.source} written to {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="relloc",
        description="Relative multi-robot localization: odometry + UWB ranges + cooperative detections.",
    )
    parser.add_argument("--version", action="version", version=f"relloc {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log warnings and details")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the simulated scenarios with every method")
    demo.add_argument("--seed", type=argtypes.seed, default=0)
    demo.add_argument("--warmup", type=float, default=10.0, help="seconds excluded from APE")
    demo.add_argument("--particles", type=argtypes.count, default=None, help="override the particle count")
    demo.add_argument("--methods", default="pf,multilateration")
    demo.add_argument("--scenarios", default="multi,single,nav")
    demo.add_argument("--out", type=Path, default=Path("out/demo"), help="folder for plots")
    demo.add_argument("--json", dest="json_path", type=Path, default=None, metavar="FILE", help="write the figures as JSON")
    demo.add_argument("--no-progress", dest="progress", action="store_false")
    _add_mode_flags(demo)
    demo.set_defaults(handler=_cmd_demo)

    run = sub.add_parser("run", help="run methods over a rosbag2 recording and evaluate them")
    run.add_argument("bag", help="bag folder (metadata.yaml) or .db3/.mcap file")
    run.add_argument("--config", required=True, help="team config (TOML), e.g. configs/tiers/...")
    run.add_argument("--methods", default="pf,multilateration")
    run.add_argument("--seed", type=argtypes.seed, default=0)
    run.add_argument("--warmup", type=float, default=5.0, help="seconds excluded from APE")
    run.add_argument("--particles", type=argtypes.count, default=None)
    run.add_argument("--models", type=Path, default=None, help="trained range-error models (for pf_ul)")
    run.add_argument("--out", type=Path, default=None, help="folder for plots and TUM trajectories")
    run.add_argument("--json", dest="json_path", type=Path, default=None, metavar="FILE")
    run.add_argument("--no-progress", dest="progress", action="store_false")
    _add_mode_flags(run)
    run.add_argument("--reference", default=None, metavar="ROBOT", help="another reference robot than the config's")
    run.set_defaults(handler=_cmd_run)

    cal = sub.add_parser("calibrate", help="estimate UWB pair biases (and heading offsets) into a config")
    cal.add_argument("source", help="a bag with motion capture, or a CSV of UWB errors")
    cal.add_argument("--config", required=True)
    cal.add_argument("--write", default=None, help="write here instead of over --config")
    cal.add_argument("--node-map", default=None, help="CSV robot numbers to nodes, e.g. 1=n_7,3=n_3")
    cal.add_argument("--headings", action="store_true", help="also heading offsets from the first mocap pose")
    cal.add_argument("--scale", action="store_true", help="also fit a range scale per pair")
    cal.set_defaults(handler=_cmd_calibrate)

    _register_optional(sub)
    return parser


def _add_mode_flags(parser: argparse.ArgumentParser) -> None:
    """Self-calibration modes (docs/self-calibration.md); the default is the config's."""
    from relloc.config import FilterConfig

    parser.add_argument(
        "--heading", choices=FilterConfig.choices("heading_mode"), default=None,
        help="compass: heading offsets from the config; estimate: estimated online",
    )
    parser.add_argument(
        "--bias", choices=FilterConfig.choices("bias_mode"), default=None,
        help="UWB pair biases from the config (calibrated) or estimated online",
    )
    parser.add_argument(
        "--odom-scale", choices=FilterConfig.choices("odom_scale_mode"), default=None,
        help="odometry scales from the config (fixed) or estimated online",
    )


def _register_optional(sub: argparse._SubParsersAction) -> None:
    """Commands that live in their own modules register themselves here."""
    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(sub)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
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
