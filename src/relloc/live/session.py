"""Zenoh sessions for the live commands: options, opening, and their command-line flags.

Every live command (``serve``, ``replay``, ``navigate``, ``sim-robots``, ``bench resources``)
opens its session the same way: peer or client mode, explicit ``--connect``/``--listen``
endpoints, multicast scouting on or off, optionally a full Zenoh JSON5 config underneath.
"""

from __future__ import annotations

import argparse
import json
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

__all__ = [
    "ZenohOptions",
    "add_zenoh_args",
    "free_tcp_port",
    "open_cli_session",
    "open_session",
    "zenoh_options_from_args",
]


@dataclass(frozen=True)
class ZenohOptions:
    """How to open a Zenoh session: mode, endpoints, scouting, or a full config file."""

    mode: Literal["peer", "client"] = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast: bool = True
    """Multicast scouting (finding peers on the LAN); off for tests and loopback benchmarks."""
    config_file: Path | None = None
    """A Zenoh JSON5 config; the options above are applied on top of it."""

    def to_config(self) -> Any:
        """The ``zenoh.Config``."""
        import zenoh

        config = (
            zenoh.Config.from_file(str(self.config_file)) if self.config_file else zenoh.Config()
        )
        config.insert_json5("mode", json.dumps(self.mode))
        if self.connect:
            config.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.listen:
            config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        if not self.multicast:
            config.insert_json5("scouting/multicast/enabled", "false")
        return config


def open_session(options: ZenohOptions) -> Any:
    """Open a ``zenoh.Session`` (the caller closes it)."""
    import zenoh

    return zenoh.open(options.to_config())


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for loopback tests and benchmarks)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def add_zenoh_args(p: argparse.ArgumentParser) -> None:
    """The Zenoh session options of every live command (``--mode``, ``--connect``, ...)."""
    g = p.add_argument_group("zenoh")
    g.add_argument("--mode", choices=("peer", "client"), default="peer")
    g.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="EP",
        help="e.g. tcp/192.168.1.10:7447 (repeatable)",
    )
    g.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="EP",
        help="e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    g.add_argument("--no-multicast", action="store_true", help="disable multicast scouting")
    g.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE",
        help="a Zenoh JSON5 config (the options above override it)",
    )
    g.add_argument(
        "--prefix", default="", help="key prefix of the robots' topics (the bridge namespace)"
    )


def zenoh_options_from_args(args: argparse.Namespace) -> ZenohOptions:
    """The :class:`ZenohOptions` of arguments added by :func:`add_zenoh_args`."""
    return ZenohOptions(
        mode=args.mode,
        connect=tuple(args.connect),
        listen=tuple(args.listen),
        multicast=not args.no_multicast,
        config_file=Path(args.zenoh_config) if args.zenoh_config else None,
    )


def open_cli_session(args: argparse.Namespace) -> Any:
    """The session of a command, or a one-line error (e.g. the --listen port is taken)."""
    from relloc.cli import UserError

    try:
        return open_session(zenoh_options_from_args(args))
    except Exception as exc:  # zenoh.ZError and config errors
        raise UserError(f"cannot open a Zenoh session: {exc}") from None
