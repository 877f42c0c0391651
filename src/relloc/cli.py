"""Command line: ``relloc demo | run | calibrate | ranging ...``.

Each command is a thin layer over the library: parse arguments, call one function, print.
Expected failures (bad config, unreadable bag, unknown method) print one clear line and exit
with status 2; they never show a traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from relloc import __version__


class UserError(Exception):
    """A problem with the user's input, reported as one line without a traceback."""


def _cmd_demo(args: argparse.Namespace) -> int:
    from relloc.demo import DemoOptions, run_demo
    from relloc.methods import parse_methods

    opts = DemoOptions(
        seed=args.seed,
        warmup=args.warmup,
        particles=args.particles,
        methods=tuple(parse_methods(args.methods)),
        scenarios=tuple(args.scenarios.split(",")),
        out=Path(args.out) if args.out else None,
        json_path=Path(args.json) if args.json else None,
        progress=not args.no_progress,
    )
    run_demo(opts)
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
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--warmup", type=float, default=10.0, help="seconds excluded from APE")
    demo.add_argument("--particles", type=int, default=None, help="override the particle count")
    demo.add_argument("--methods", default="pf,multilateration")
    demo.add_argument("--scenarios", default="multi,single")
    demo.add_argument("--out", default="out/demo", help="folder for plots")
    demo.add_argument("--json", default=None, metavar="FILE", help="write the figures as JSON")
    demo.add_argument("--no-progress", action="store_true")
    demo.set_defaults(handler=_cmd_demo)

    _register_optional(sub)
    return parser


def _register_optional(sub: argparse._SubParsersAction) -> None:
    """Commands that live in their own modules register themselves here."""
    from relloc import commands

    commands.register_all(sub)


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
        if _is_user_error(exc):
            print(f"relloc {args.command}: error: {exc}", file=sys.stderr)
            return 2
        raise


def _is_user_error(exc: Exception) -> bool:
    from relloc.config import ConfigError
    from relloc.methods import MethodError

    known: tuple[type[Exception], ...] = (UserError, ConfigError, MethodError, FileNotFoundError)
    try:
        from relloc.sources.rosbag import BagError

        known += (BagError,)
    except ImportError:
        pass
    return isinstance(exc, known)


if __name__ == "__main__":
    raise SystemExit(main())
