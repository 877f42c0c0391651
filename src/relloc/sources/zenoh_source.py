"""Live robots over Eclipse Zenoh as a stream of relloc events.

This module is the Zenoh transport: which key expressions to subscribe to, and how a payload
gets from Zenoh's threads to the engine's. What the payloads become (routes, conversion, header
clock, zero-stamp restamping, reorder buffer, counters) is the shared ingestion layer,
:mod:`relloc.sources.ingest`, which the rosbag source uses too.

Keys
----
ROS 2 robots reach Zenoh through ``zenoh-bridge-ros2dds`` (or ``rmw_zenoh``); the bridge puts
each message, serialised as ROS 2 CDR exactly as a rosbag2 file stores it, on the key
expression named after the topic: ``/tb1/odom`` -> ``tb1/odom`` (the leading slash dropped), below
the bridge's namespace if it has one. :func:`build_routes` puts the team's routes
(:func:`~relloc.sources.ingest.team_routes`: odometry, UWB ranges of every pair in both node
orders, and detections only when the methods use them, since decoding them costs CPU for
nothing otherwise) on their keys: ``[<global prefix>/][<robot zenoh_scope>/]<topic without
leading slash>``. A range topic belongs to no single robot, so it is subscribed below the scope
of each of its two robots.

Threads
-------
Zenoh calls :meth:`ZenohSource.on_sample` on its own threads. That callback only copies the
payload, notes the receive wall time (and the publisher's send time, when a relloc replay
attached it) and puts it on a bounded queue; decoding, reordering and everything after happen
on the one engine thread that calls :meth:`ZenohSource.poll`. The filter state therefore never
sees two threads, and a slow engine cannot block Zenoh's network threads (a full queue drops
the sample and counts it as ``queue_full``).

Time and order
--------------
Receive times are wall times; the header clock learns its offset from every stamped message as
it comes (``clock_rate`` > 1 when a recording is replayed faster than real time). The reorder
buffer holds events for at most ``reorder_window`` seconds of header time (or that window in
wall time, divided by the clock rate, when nothing newer comes) and releases them in stamp
order; what still comes later than an event already released is passed on and counted as
``out_of_order``, and the localizer decides (it accepts a range up to one update period late
and rejects, counting, older ones and odometry going backwards). ``0`` passes events through as
they come, which the localizer tolerates by design (see ``docs/live.md``).

Rejections
----------
Nothing that arrives can crash the engine. Besides the ingestion layer's rejections
(``decode_error``, unusable values), a key this source has no route for (``unknown_key``: only
possible with the ``subscribe_all`` wildcard subscription) and a full queue (``queue_full``) are
dropped, counted per reason in :attr:`ZenohSource.stats` and logged (the first time and every
1000th).
"""

from __future__ import annotations

import logging
import queue
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any

from relloc.config import ConfigError, TeamConfig
from relloc.events import Event
from relloc.ros.messages import typestore
from relloc.sources.ingest import (
    Converter,
    HeaderClock,
    IngestStats,
    ReorderBuffer,
    Route,
    team_routes,
)

__all__ = [
    "SENT_TIME_TAG",
    "Arrival",
    "ZenohSource",
    "ZenohSourceOptions",
    "build_routes",
    "decode_sent_time",
    "encode_sent_time",
    "key_for_topic",
]

log = logging.getLogger(__name__)

SENT_TIME_TAG = b"rlst"
"""Prefix of the 12-byte Zenoh attachment ``rlst`` + float64 (little endian) send wall time that
``relloc replay`` puts on every message, so that end-to-end latency can be measured."""


def encode_sent_time(t: float) -> bytes:
    """The attachment carrying a publisher's send wall time (s since the epoch)."""
    return SENT_TIME_TAG + struct.pack("<d", t)


def decode_sent_time(attachment: bytes | None) -> float | None:
    """The send wall time of an attachment made by :func:`encode_sent_time`, else ``None``."""
    if attachment is None or len(attachment) != 12 or not attachment.startswith(SENT_TIME_TAG):
        return None
    return float(struct.unpack_from("<d", attachment, 4)[0])


def key_for_topic(topic: str, *, prefix: str = "", scope: str = "") -> str:
    """The Zenoh key of a ROS topic under the bridge convention.

    ``key_for_topic("/tb1/odom") == "tb1/odom"``; ``prefix`` (global) and ``scope`` (the robot's
    ``zenoh_scope``) are prepended in that order: ``key_for_topic("/odom", prefix="lab",
    scope="tb1") == "lab/tb1/odom"``.
    """
    parts = [p.strip("/") for p in (prefix, scope, topic)]
    key = "/".join(p for p in parts if p)
    if not key or any(c in key for c in "*$?#") or "//" in key:
        raise ConfigError(
            f"topic {topic!r} (prefix {prefix!r}, scope {scope!r}) is not a valid key"
        )
    return key


def build_routes(
    config: TeamConfig,
    *,
    prefix: str = "",
    odometry: bool = True,
    ranges: bool = True,
    detections: bool = True,
) -> dict[str, Route]:
    """Every key the team's data arrives on, mapped to its :class:`~relloc.sources.ingest.Route`.

    Raises :class:`~relloc.config.ConfigError` if two routes would share one key (e.g. two robots
    configured with the same odometry topic and no scopes).
    """
    routes: dict[str, Route] = {}
    for route in team_routes(config, odometry=odometry, ranges=ranges, detections=detections):
        robots = (route.robot, route.robot_b) if route.robot_b else (route.robot,)
        for scope in dict.fromkeys(config.robot(r).zenoh_scope for r in robots):
            key = key_for_topic(route.topic, prefix=prefix, scope=scope)
            old = routes.get(key)
            if old is not None and old != route:
                raise ConfigError(
                    f"Zenoh key {key!r} would carry both {old.kind} of {old.robot} and "
                    f"{route.kind} of {route.robot}; give the robots a zenoh_scope"
                )
            routes[key] = route
    return routes


@dataclass(frozen=True, slots=True)
class Arrival:
    """An event with where and when its message arrived (for latency tracing)."""

    event: Event
    key: str
    received: float
    """Wall time (s since the epoch) the Zenoh callback got the message."""
    sent: float | None = None
    """Wall time the publisher sent it, when a relloc replay attached it."""


@dataclass(frozen=True)
class ZenohSourceOptions:
    """How the live source subscribes and orders events."""

    prefix: str = ""
    """Global key prefix (e.g. the bridge's namespace), before each robot's ``zenoh_scope``."""
    reorder_window: float = 0.0
    """Header-time window (s) of the reorder buffer; 0 passes events through as they come."""
    clock_rate: float = 1.0
    """Header seconds per wall second (a recording replayed at ``--rate 2``: 2)."""
    odometry: bool = True
    ranges: bool = True
    detections: bool = True
    subscribe_all: bool = False
    """Subscribe to ``<prefix>/**`` instead of each key (keys without a route count as
    ``unknown_key``): shows what else is published, at the cost of receiving it."""
    queue_size: int = 10000
    """Samples waiting for the engine thread; beyond that new ones are dropped (``queue_full``)."""


_WAKE = object()


class ZenohSource:
    """Subscribes to a team's topics over Zenoh and turns the messages into ordered events.

    Use :meth:`attach` with an open ``zenoh.Session``, then call :meth:`poll` in a loop on the
    engine thread; :meth:`detach` undeclares the subscribers (the session belongs to the
    caller). :meth:`handle` is the same path without Zenoh, for tests and other transports.
    """

    def __init__(self, config: TeamConfig, options: ZenohSourceOptions | None = None) -> None:
        self.config = config
        self.options = opts = options or ZenohSourceOptions()
        self.routes = build_routes(
            config,
            prefix=opts.prefix,
            odometry=opts.odometry,
            ranges=opts.ranges,
            detections=opts.detections,
        )
        store = typestore()
        for key, route in self.routes.items():
            missing = [t for t in route.msgtypes if t not in store.fielddefs]
            if missing:  # cannot happen with the shipped type store; guards a broken install
                raise ConfigError(f"message type(s) {missing} of {key!r} are unknown")
        self.stats = IngestStats()
        self.clock = HeaderClock(opts.clock_rate, config.clock_offset)
        self.buffer: ReorderBuffer[Arrival] = ReorderBuffer(
            opts.reorder_window, hold=opts.reorder_window / opts.clock_rate
        )
        self._converter = Converter(self.stats, self.clock, log)
        # SimpleQueue: C-implemented, the cheapest hand-over between threads CPython has; it
        # is unbounded, so the size limit is checked (approximately) before each put.
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._max_queue = opts.queue_size
        self._subscribers: list[Any] = []
        self._lock = threading.Lock()
        self._queue_full = 0

    # ------------------------------------------------------------------ zenoh side
    @property
    def keys(self) -> list[str]:
        """The keys subscribed to (sorted)."""
        return sorted(self.routes)

    def attach(self, session: Any) -> None:
        """Declare the subscribers on ``session`` (a ``zenoh.Session``)."""
        if self.options.subscribe_all:
            prefix = self.options.prefix.strip("/")
            exprs = [f"{prefix}/**" if prefix else "**"]
        else:
            exprs = self.keys
        for expr in exprs:
            self._subscribers.append(session.declare_subscriber(expr, self.on_sample))
        log.info("subscribed to %d key expression(s): %s", len(exprs), ", ".join(exprs))

    def detach(self) -> None:
        """Undeclare the subscribers (idempotent)."""
        subs, self._subscribers = self._subscribers, []
        for sub in subs:
            try:
                sub.undeclare()
            except Exception as exc:  # the session may already be closed
                log.debug("undeclaring a subscriber failed: %s", exc)

    def on_sample(self, sample: Any) -> None:
        """Zenoh callback (Zenoh's threads): copy, time and enqueue; nothing else."""
        received = time.time()
        attachment = sample.attachment
        sent = decode_sent_time(attachment.to_bytes()) if attachment is not None else None
        if self._queue.qsize() < self._max_queue:
            self._queue.put((str(sample.key_expr), sample.payload.to_bytes(), received, sent))
        else:
            with self._lock:
                self._queue_full += 1
                n = self._queue_full
            if n == 1 or n % 1000 == 0:
                log.warning("engine falling behind: %d samples dropped (queue full)", n)

    def wake(self) -> None:
        """Make a blocked :meth:`poll` return now (e.g. on shutdown)."""
        self._queue.put(_WAKE)

    @property
    def queue_depth(self) -> int:
        return self._queue.qsize()

    # ------------------------------------------------------------------ engine side
    def poll(self, timeout: float) -> list[Arrival]:
        """Wait up to ``timeout`` s for messages, handle all queued ones, return due events.

        Returns early when the reorder buffer has an event due. Call from one thread only.
        """
        due = self.buffer.next_due()
        wait = timeout if due is None else max(0.0, min(timeout, due - time.time()))
        try:
            item = self._queue.get(timeout=wait) if wait > 0 else self._queue.get_nowait()
        except queue.Empty:
            item = None
        while item is not None:
            if item is not _WAKE:
                self.handle(*item)
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                item = None
        self._sync_queue_full()
        return self.release(time.time())

    def drain(self) -> list[Arrival]:
        """Handle everything still queued and release everything held (shutdown)."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if item is not _WAKE:
                self.handle(*item)
        self._sync_queue_full()
        self.stats.clock_offset = self.clock.overall
        return self.flush()

    def handle(
        self, key: str, payload: bytes | bytearray | memoryview, received: float, sent: float | None = None
    ) -> None:
        """Decode one message and put its event in the reorder buffer (or count why not)."""
        route = self.routes.get(key)
        if route is None:
            self._converter.reject("unknown_key", key)
            return
        event = self._converter.convert(route, key, payload, received)
        if event is not None:
            self.buffer.push(event.t, Arrival(event, key, received, sent), received)
            self.buffer.advance(event.t)

    def release(self, now: float) -> list[Arrival]:
        """Events due at wall time ``now`` (for callers driving :meth:`handle` themselves)."""
        return self._released(self.buffer.pop_ready(now))

    def flush(self) -> list[Arrival]:
        """Every held event, in stamp order."""
        return self._released(self.buffer.flush())

    def _released(self, arrivals: list[Arrival]) -> list[Arrival]:
        stats = self.stats
        for arrival in arrivals:
            stats.emitted(arrival.event)
        stats.out_of_order = self.buffer.late
        return arrivals

    def _sync_queue_full(self) -> None:
        with self._lock:
            n = self._queue_full
        if n:
            self.stats.rejected["queue_full"] = n
