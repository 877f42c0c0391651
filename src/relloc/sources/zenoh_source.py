"""Live robots over Eclipse Zenoh as a stream of relloc events.

What it reads
-------------
ROS 2 robots reach Zenoh through ``zenoh-bridge-ros2dds`` (or ``rmw_zenoh``); the bridge puts
each message, serialised as ROS 2 CDR exactly as a rosbag2 file stores it, on the key
expression named after the topic: ``/tb1/odom`` -> ``tb1/odom`` (the leading slash dropped), below
the bridge's namespace if it has one. :func:`build_routes` derives, from the team config, the
keys this source subscribes to and how each becomes an event:

* each robot's ``odom_topic`` -> :class:`~relloc.events.OdometryEvent`;
* ``uwb.range_topic`` (``{a}``/``{b}`` = node ids) for every pair of the team's robots, in both
  node orders (the UWB driver may publish either) -> ``RangeEvent``;
* each robot's ``detection_topic`` -> ``DetectionEvent`` in the body frame (camera extrinsics
  applied), only when the methods use detections (decoding them costs CPU for nothing
  otherwise).

A key is ``[<global prefix>/][<robot zenoh_scope>/]<topic without leading slash>``. A range
topic belongs to no single robot, so it is subscribed below the scope of each of its two
robots.

Threads
-------
Zenoh calls :meth:`ZenohSource.on_sample` on its own threads. That callback only copies the
payload, notes the receive wall time (and the publisher's send time, when a relloc replay
attached it) and puts it on a bounded queue; decoding, reordering and everything after happen
on the one engine thread that calls :meth:`ZenohSource.poll`. The filter state therefore never
sees two threads, and a slow engine cannot block Zenoh's network threads (a full queue drops
the sample and counts it as ``queue_full``).

Time
----
Events carry **header stamps**, as in the rosbag source. A message with an all-zero stamp (or
of a robot flagged ``odom_zero_stamps``) is stamped with its receive time put on the header
clock by :class:`HeaderClock`: ``header = offset + clock_rate * wall``, the offset estimated as
the running median over recent stamped messages of the same kind (``clock_rate`` > 1 when a
recording is replayed faster than real time; ``TeamConfig.clock_offset`` fixes the offset).

Messages of different topics arrive out of header order (odometry lags the UWB by some 40 ms,
detections by 300 ms). :class:`ReorderBuffer` holds events for at most ``reorder_window``
seconds of header time and releases them in stamp order; what still comes later than an event
already released is passed on and counted as ``out_of_order``, and the localizer decides (it
accepts a range up to one update period late and rejects, counting, older ones and odometry
going backwards). The window is latency: every event waits up to that long. ``0`` passes events
through as they come, which the localizer tolerates by design (see ``docs/live.md``).

Rejections
----------
Nothing that arrives can crash the engine. A payload that does not decode as the key's type
(``decode_error``), a key this source has no route for (``unknown_key``: only possible with the
``subscribe_all`` wildcard subscription), unusable values (``range_nonfinite``,
``range_nonpositive``, ``detection_zero_position``...) and a full queue (``queue_full``) are
dropped, counted per reason in :attr:`ZenohSource.stats` and logged (the first time and every
1000th).
"""

from __future__ import annotations

import heapq
import logging
import math
import queue
import statistics
import struct
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any, Literal

from relloc.config import CameraConfig, ConfigError, TeamConfig
from relloc.events import Event, OdometryEvent, RangeEvent
from relloc.ros.cdr import decode_odometry, decode_range
from relloc.ros.messages import (
    ODOMETRY,
    POSE_ARRAY,
    RANGE,
    SPATIAL_DETECTION_ARRAY,
    MessageDecodeError,
    decode,
    detections_to_event,
    odometry_to_event,
    range_rejection,
    stamp_to_sec,
    typestore,
)

__all__ = [
    "SENT_TIME_TAG",
    "Arrival",
    "HeaderClock",
    "LiveSourceStats",
    "ReorderBuffer",
    "Route",
    "ZenohSource",
    "ZenohSourceOptions",
    "build_routes",
    "decode_sent_time",
    "encode_sent_time",
    "key_for_topic",
]

log = logging.getLogger(__name__)

Kind = Literal["odometry", "range", "detection"]

_DETECTION_TYPES = {"depthai": (SPATIAL_DETECTION_ARRAY,), "posearray": (POSE_ARRAY,)}

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


@dataclass(frozen=True)
class Route:
    """How the messages on one key become events."""

    key: str
    topic: str
    kind: Kind
    msgtypes: tuple[str, ...]
    """Message types tried in order (an unspecified detection format accepts both)."""
    robot: str
    robot_b: str = ""
    node_a: str = ""
    node_b: str = ""
    camera: CameraConfig | None = None
    zero_stamps: bool = False


def build_routes(
    config: TeamConfig,
    *,
    prefix: str = "",
    odometry: bool = True,
    ranges: bool = True,
    detections: bool = True,
) -> dict[str, Route]:
    """Every key the team's data arrives on, mapped to its :class:`Route`.

    Raises :class:`~relloc.config.ConfigError` if two routes would share one key (e.g. two robots
    configured with the same odometry topic and no scopes).
    """
    routes: dict[str, Route] = {}

    def add(route: Route) -> None:
        old = routes.get(route.key)
        if old is not None and old != route:
            raise ConfigError(
                f"Zenoh key {route.key!r} would carry both {old.kind} of {old.robot} and "
                f"{route.kind} of {route.robot}; give the robots a zenoh_scope"
            )
        routes[route.key] = route

    for robot in config.robots:
        if odometry and robot.odom_topic:
            key = key_for_topic(robot.odom_topic, prefix=prefix, scope=robot.zenoh_scope)
            add(
                Route(
                    key,
                    robot.odom_topic,
                    "odometry",
                    (ODOMETRY,),
                    robot.name,
                    zero_stamps=robot.odom_zero_stamps,
                )
            )
        if detections and robot.detection_topic:
            fmt = robot.detection_format
            types = _DETECTION_TYPES.get(fmt, (SPATIAL_DETECTION_ARRAY, POSE_ARRAY))
            key = key_for_topic(robot.detection_topic, prefix=prefix, scope=robot.zenoh_scope)
            add(
                Route(
                    key, robot.detection_topic, "detection", types, robot.name, camera=robot.camera
                )
            )
    if ranges:
        template = config.uwb.range_topic
        if "{a}" not in template or "{b}" not in template:
            raise ConfigError(f"uwb.range_topic {template!r} must contain both {{a}} and {{b}}")
        with_nodes = [r for r in config.robots if r.uwb_node]
        for ra, rb in combinations(with_nodes, 2):
            for first, second in ((ra, rb), (rb, ra)):
                topic = template.format(a=first.uwb_node, b=second.uwb_node)
                for scope in dict.fromkeys((first.zenoh_scope, second.zenoh_scope)):
                    key = key_for_topic(topic, prefix=prefix, scope=scope)
                    add(
                        Route(
                            key,
                            topic,
                            "range",
                            (RANGE,),
                            first.name,
                            robot_b=second.name,
                            node_a=first.uwb_node,
                            node_b=second.uwb_node,
                        )
                    )
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


class HeaderClock:
    """Puts receive wall times on the header clock, for messages with zero stamps.

    ``header ~ offset + rate * wall``: the offset of each kind of message is the running median
    of ``stamp - rate * received`` over its last ``window`` stamped messages (odometry lags the
    UWB, so kinds are kept apart, as the rosbag source does); a kind never seen stamped uses the
    median over the kinds seen, and with nothing seen at all the wall clock itself
    (``rate * wall``; live ROS stamps are wall time). ``fixed_offset`` overrides every estimate.
    """

    def __init__(
        self, rate: float = 1.0, fixed_offset: float | None = None, window: int = 200
    ) -> None:
        if not rate > 0:
            raise ValueError(f"clock rate must be positive, got {rate}")
        self.rate = float(rate)
        self.fixed_offset = fixed_offset
        self._samples: dict[str, deque[float]] = {}
        self._window = window

    def observe(self, kind: str, stamp: float, received: float) -> None:
        """Learn from a message that has a real header stamp."""
        self._samples.setdefault(kind, deque(maxlen=self._window)).append(
            stamp - self.rate * received
        )

    def offset(self, kind: str) -> float:
        """Current estimate of ``header - rate * wall`` for ``kind``."""
        if self.fixed_offset is not None:
            return self.fixed_offset
        own = self._samples.get(kind)
        if own:
            return statistics.median(own)
        medians = [statistics.median(s) for s in self._samples.values() if s]
        return statistics.median(medians) if medians else 0.0

    def stamp(self, kind: str, received: float) -> float:
        """Header-clock time of a message of ``kind`` received at wall time ``received``."""
        return self.offset(kind) + self.rate * received


class ReorderBuffer:
    """Releases events in header-stamp order after holding each for at most a window.

    An event leaves once an event stamped ``window`` seconds after it has arrived, or once it
    has waited ``window / clock_rate`` seconds of wall time (so a quiet team is not held back);
    events leave in stamp order, and one older than an event already released leaves at once. Memory is bounded by a window's worth of messages. ``window=0``
    passes every event straight through. An event older than one already released still goes
    out (counted in :attr:`out_of_order`): the localizer decides whether it is too late.
    """

    def __init__(self, window: float, clock_rate: float = 1.0) -> None:
        if window < 0:
            raise ValueError(f"reorder window must be >= 0, got {window}")
        self.window = float(window)
        self.hold = self.window / clock_rate
        self._heap: list[tuple[float, int, Arrival]] = []
        self._seq = 0
        self._newest = -math.inf
        self.last_released = -math.inf
        self.out_of_order = 0
        self.max_depth = 0

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, item: Arrival) -> None:
        t = item.event.t
        heapq.heappush(self._heap, (t, self._seq, item))
        self._seq += 1
        self._newest = max(self._newest, t)
        self.max_depth = max(self.max_depth, len(self._heap))

    def pop_ready(self, now: float) -> list[Arrival]:
        """Events due at wall time ``now``, in stamp order."""
        out: list[Arrival] = []
        horizon = self._newest - self.window
        while self._heap:
            t, _, item = self._heap[0]
            late = t < self.last_released  # order is lost already: holding it cannot help
            if not late and t > horizon and now - item.received < self.hold:
                break
            heapq.heappop(self._heap)
            out.append(self._release(item))
        return out

    def flush(self) -> list[Arrival]:
        """Everything held, in stamp order (shutdown)."""
        out = []
        while self._heap:
            out.append(self._release(heapq.heappop(self._heap)[2]))
        return out

    def next_due(self) -> float | None:
        """Wall time at which the oldest held event is released by waiting, or ``None``."""
        return self._heap[0][2].received + self.hold if self._heap else None

    def _release(self, item: Arrival) -> Arrival:
        t = item.event.t
        if t < self.last_released:
            self.out_of_order += 1
        else:
            self.last_released = t
        return item


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


@dataclass
class LiveSourceStats:
    """What the live source received, emitted and rejected."""

    received: Counter[str] = field(default_factory=Counter)
    """Messages per key (only keys with a route)."""
    events: Counter[str] = field(default_factory=Counter)
    """Events emitted per kind."""
    rejected: Counter[str] = field(default_factory=Counter)
    """Dropped messages or values by reason."""
    restamped: Counter[str] = field(default_factory=Counter)
    """Messages per key stamped from the receive time (zero header stamps)."""
    out_of_order: int = 0
    """Events released after a later-stamped one (passed on; the localizer judges them)."""
    last_received: dict[str, float] = field(default_factory=dict)
    """Per robot, the wall time of its last message (any kind): who went quiet."""

    def as_dict(self) -> dict[str, Any]:
        """Plain-dict view for JSON status and ``--json`` output."""
        return {
            "received": dict(self.received),
            "events": dict(self.events),
            "rejected": dict(self.rejected),
            "restamped": dict(self.restamped),
            "out_of_order": self.out_of_order,
        }


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
        for route in self.routes.values():
            missing = [t for t in route.msgtypes if t not in store.fielddefs]
            if missing:  # cannot happen with the shipped type store; guards a broken install
                raise ConfigError(f"message type(s) {missing} of {route.key!r} are unknown")
        self.stats = LiveSourceStats()
        self.clock = HeaderClock(opts.clock_rate, config.clock_offset)
        self.buffer = ReorderBuffer(opts.reorder_window, opts.clock_rate)
        # SimpleQueue: C-implemented, the cheapest hand-over between threads CPython has; it
        # is unbounded, so the size limit is checked (approximately) before each put.
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._max_queue = opts.queue_size
        self._subscribers: list[Any] = []
        self._lock = threading.Lock()
        self._queue_full = 0
        self._restamped_last: dict[str, float] = {}

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
        return self.buffer.pop_ready(time.time())

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
        return self.buffer.flush()

    def handle(
        self, key: str, payload: bytes | bytearray | memoryview, received: float, sent: float | None = None
    ) -> None:
        """Decode one message and put its event in the reorder buffer (or count why not)."""
        if not isinstance(payload, bytes):
            payload = bytes(payload)  # the decoders hash and slice it
        route = self.routes.get(key)
        if route is None:
            self._reject("unknown_key", key)
            return
        self.stats.received[key] += 1
        self.stats.last_received[route.robot] = received
        if route.robot_b:
            self.stats.last_received[route.robot_b] = received
        event = self._convert(route, payload, received)
        if event is None:
            return
        self.stats.events[route.kind] += 1
        self.buffer.push(Arrival(event, key, received, sent))
        self.stats.out_of_order = self.buffer.out_of_order

    def release(self, now: float) -> list[Arrival]:
        """Events due at wall time ``now`` (for callers driving :meth:`handle` themselves)."""
        out = self.buffer.pop_ready(now)
        self.stats.out_of_order = self.buffer.out_of_order
        return out

    def flush(self) -> list[Arrival]:
        """Every held event, in stamp order."""
        out = self.buffer.flush()
        self.stats.out_of_order = self.buffer.out_of_order
        return out

    # ------------------------------------------------------------------ conversion
    def _convert(self, route: Route, payload: bytes, received: float) -> Event | None:
        fast = self._fast_fields(route, payload)
        msg = None
        if fast is None:
            for msgtype in route.msgtypes:
                try:
                    msg = decode(payload, msgtype)
                    break
                except MessageDecodeError as exc:
                    error = exc
            if msg is None:
                self._reject("decode_error", route.key, str(error))
                return None
            stamp = stamp_to_sec(msg.header.stamp)
        else:
            stamp = fast[0]
        if route.zero_stamps or stamp == 0.0:
            # Arrival order is the topic's order: keep the restamped times increasing even while
            # the clock estimate moves.
            previous = self._restamped_last.get(route.key, -math.inf)
            stamp = max(self.clock.stamp(route.kind, received), previous + 1e-6)
            self._restamped_last[route.key] = stamp
            self.stats.restamped[route.key] += 1
        else:
            self.clock.observe(route.kind, stamp, received)
        if route.kind == "odometry":
            if fast is not None:
                _, x, y, yaw, v, w = fast
                return OdometryEvent(t=stamp, robot=route.robot, x=x, y=y, yaw=yaw, v=v, w=w)
            return odometry_to_event(msg, route.robot, t=stamp)
        if route.kind == "range":
            distance = fast[1] if fast is not None else float(msg.range)
            reason = range_rejection(distance)
            if reason is not None:
                self._reject(f"range_{reason}", route.key)
                return None
            return RangeEvent(
                t=stamp,
                robot_a=route.robot,
                robot_b=route.robot_b,
                distance=distance,
                node_a=route.node_a,
                node_b=route.node_b,
            )
        assert route.camera is not None
        det, rejected = detections_to_event(msg, route.robot, route.camera, t=stamp)
        for reason, n in rejected.items():
            self.stats.rejected[f"detection_{reason}"] += n
        return det

    @staticmethod
    def _fast_fields(route: Route, payload: bytes) -> tuple[float, ...] | None:
        """The hot messages' fields straight from the bytes (:mod:`relloc.ros.cdr`), or
        ``None``: then the full ``rosbags`` decoder decodes the payload or says why not."""
        if route.kind == "odometry" and route.msgtypes[0] == ODOMETRY:
            return decode_odometry(payload)
        if route.kind == "range" and route.msgtypes[0] == RANGE:
            return decode_range(payload)
        return None

    def _reject(self, reason: str, key: str, detail: str = "") -> None:
        self.stats.rejected[reason] += 1
        n = self.stats.rejected[reason]
        if n == 1 or n % 1000 == 0:
            log.warning("rejected a message on %r (%s, %d so far) %s", key, reason, n, detail)

    def _sync_queue_full(self) -> None:
        with self._lock:
            n = self._queue_full
        if n:
            self.stats.rejected["queue_full"] = n
        self.stats.out_of_order = self.buffer.out_of_order
