"""A Foxglove WebSocket client for the tests and the benchmark, as the app is one.

It speaks ``foxglove.sdk.v1`` (what the SDK's server accepts) with ``websockets`` on a thread
of its own: reads the advertised channels, subscribes to the topics asked for and decodes every
message (protobuf from the channel's advertised descriptor set into a message, JSON as JSON), keeping
``(receive time, decoded)`` per topic.
"""

from __future__ import annotations

import asyncio
import base64
import json
import struct
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

SUBPROTOCOL = "foxglove.sdk.v1"


def _protobuf_decoder(schema_name: str, schema_b64: str) -> Callable[[bytes], Any]:
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
    pool = descriptor_pool.DescriptorPool()
    for f in files.file:
        pool.Add(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))

    return cls.FromString


class FoxgloveClient:
    """Connects to ``ws://host:port`` and subscribes to every advertised topic that
    ``wanted`` accepts (all by default); :attr:`messages` fills as they come."""

    def __init__(
        self, host: str, port: int, wanted: Callable[[str], bool] = lambda topic: True
    ) -> None:
        self.url = f"ws://{host}:{port}"
        self.wanted = wanted
        self.channels: dict[str, dict[str, Any]] = {}
        """Topic -> the advertised channel."""
        self.messages: dict[str, list[tuple[float, Any]]] = defaultdict(list)
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def topics(self) -> set[str]:
        with self._lock:
            return set(self.channels)

    def received(self, topic: str) -> list[tuple[float, Any]]:
        with self._lock:
            return list(self.messages.get(topic, ()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except websockets.ConnectionClosedOK:
            pass  # the server stopped
        except BaseException as exc:  # reported to the test through .error
            self.error = exc

    async def _main(self) -> None:
        async with websockets.connect(
            self.url, subprotocols=[SUBPROTOCOL], max_size=None, open_timeout=30
        ) as ws:
            subs: dict[int, tuple[str, Callable[[bytes], Any]]] = {}
            while not self._stop.is_set():
                try:
                    raw = await asyncio.wait_for(ws.recv(), 0.1)
                except TimeoutError:
                    continue
                if isinstance(raw, bytes):
                    if raw[0] != 0x01:  # message data
                        continue
                    (sub_id,) = struct.unpack_from("<I", raw, 1)
                    topic, decode = subs[sub_id]
                    decoded = decode(raw[13:])
                    with self._lock:
                        self.messages[topic].append((time.time(), decoded))
                    continue
                msg = json.loads(raw)
                if msg.get("op") != "advertise":
                    continue
                new = []
                for ch in msg["channels"]:
                    with self._lock:
                        self.channels[ch["topic"]] = ch
                    if not self.wanted(ch["topic"]):
                        continue
                    if ch["encoding"] == "json":
                        decode: Callable[[bytes], Any] = json.loads
                    else:
                        decode = _protobuf_decoder(ch["schemaName"], ch["schema"])
                    sub_id = len(subs) + 1
                    subs[sub_id] = (ch["topic"], decode)
                    new.append({"id": sub_id, "channelId": ch["id"]})
                if new:
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
