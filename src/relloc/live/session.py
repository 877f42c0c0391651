"""Zenoh sessions of the live engine: options and opening.

Every live part (server, replay, navigation, simulated robots, benchmarks) opens its session the
same way: peer or client mode, explicit connect/listen endpoints, multicast scouting on or off,
optionally a full Zenoh JSON5 config underneath. The command-line flags that fill
:class:`ZenohOptions` are in :mod:`relloc.cli.common`.
"""

from __future__ import annotations

import json
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

__all__ = [
    "ZenohOptions",
    "free_tcp_port",
    "open_session",
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
