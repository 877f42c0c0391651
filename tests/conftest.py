"""Shared test fixtures: where the TIERS recordings are, a tiny rosbag2 writer, and two Zenoh
sessions on loopback.

The recordings live in ``../shared/data`` next to the repository root and are never copied into
the repository; tests that need them take the ``shared_data`` fixture, which skips (with the
reason) when the folder is absent.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
"""``../shared/data`` next to the repository root."""

BagMessage = tuple[str, str, float, Any]
"""``(topic, message type, receive time in s, message object)`` for :func:`bag_writer`."""


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared data folder (``tiers/`` holds the TIERS bags), or skip the test."""
    if not (SHARED_DATA / "tiers").is_dir():
        pytest.skip(f"../shared/data not found: {SHARED_DATA} (the TIERS recordings)")
    return SHARED_DATA


@pytest.fixture
def bag_writer() -> Callable[..., Path]:
    """A function writing messages to a new rosbag2 bag (sqlite3 or mcap) and returning its path.

    Topics are registered in first-appearance order; the relloc type store of a distribution
    (with the custom detection types) serialises the messages.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    from relloc.ros.messages import encode, typestore

    def write(
        path: Path,
        messages: Iterable[BagMessage],
        *,
        storage: str = "sqlite3",
        distro: str = "jazzy",
    ) -> Path:
        """Messages in ``distro``'s layouts, with that distribution's definitions stored."""
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        store = typestore(distro)
        with Writer(path, version=9, storage_plugin=plugin) as writer:
            conns: dict[str, Any] = {}
            for topic, msgtype, recv, msg in messages:
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
                writer.write(conns[topic], round(recv * 1e9), encode(msg, msgtype, distro))
        return path

    return write


@pytest.fixture
def sessions() -> Iterator[tuple[Any, Any]]:
    """Two peer Zenoh sessions on loopback (a free TCP port on 127.0.0.1, no multicast
    scouting): (server side listening, client side connecting); both closed afterwards."""
    from relloc.live import ZenohOptions, free_tcp_port, open_session

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    server = open_session(ZenohOptions(listen=(endpoint,), multicast=False))
    client = open_session(ZenohOptions(connect=(endpoint,), multicast=False))
    try:
        yield server, client
    finally:
        client.close()
        server.close()
