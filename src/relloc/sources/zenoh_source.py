"""Live robots over Eclipse Zenoh as a stream of relloc events.

This module is the Zenoh transport only: which key expressions to subscribe to (the
interface's, :class:`~relloc.ros.interfaces.RosInterface`; the routes from
:func:`~relloc.sources.zenoh_keys.build_routes`), and how a payload gets from Zenoh's threads
to the engine's. What payloads become is the shared ingestion layer,
:mod:`relloc.sources.ingest`, which the rosbag source uses too.

* Zenoh calls :meth:`ZenohSource.on_sample` on its own threads; it only copies the payload,
  notes the receive time and appends to a bounded queue. Decoding, reordering and everything
  after happen on the engine thread in :meth:`ZenohSource.poll`, so the filter state never
  sees two threads and a slow engine never blocks Zenoh's network threads.
* The engine thread is woken only for a message that could make an estimate (the consumer's
  :class:`~relloc.events.WakeRule`, :meth:`ZenohSource.rearm`): waking per message was most
  of the live engine's CPU.
* Nothing that arrives can crash the engine: unusable samples are dropped and counted per
  reason in :attr:`ZenohSource.stats`.

Keys, threads, time and order, rejections in full: ``docs/explanation/internals.md`` and
``docs/explanation/live-engine.md``.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from relloc.config import ConfigError, TeamConfig
from relloc.events import Event, WakeRule
from relloc.ros.distros import HASH_NOT_SUPPORTED, layouts
from relloc.ros.interfaces import (
    RosInterface,
    dds_type_name,
    decode_sent_time,
)
from relloc.ros.zenoh_node import ZenohNode
from relloc.sensors import sensor
from relloc.sensors.builtin import GROUND_TRUTH
from relloc.sources.clock import HeaderClock
from relloc.sources.ingest import Converter, IngestStats
from relloc.sources.reorder import ReorderBuffer
from relloc.sources.rmw_envelope import RmwEnvelope, TransportStats
from relloc.sources.zenoh_keys import build_routes, route_scopes, truth_scopes

__all__ = ["Arrival", "ZenohSource", "ZenohSourceOptions"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Arrival:
    """An event with where and when its message arrived (for latency tracing)."""

    event: Event
    key: str
    received: float
    """Wall time (s since the epoch) the Zenoh callback got the message."""
    sent: float | None = None
    """Wall time the publisher sent it: a relloc publisher's attachment on the bridge, the
    source timestamp of the rmw_zenoh attachment."""


@dataclass(frozen=True)
class ZenohSourceOptions:
    """How the live source subscribes and orders events."""

    prefix: str = ""
    """Global key prefix (e.g. the bridge's namespace), before each robot's ``zenoh_scope``."""
    interface: RosInterface = field(default_factory=RosInterface)
    """The key format and attachments of the robots (``bridge`` or ``rmw_zenoh``)."""
    reorder_window: float = 0.0
    """Header-time window (s) of the reorder buffer; 0 passes events through as they come."""
    clock_rate: float = 1.0
    """Header seconds per wall second (a recording replayed at ``--rate 2``: 2)."""
    reorder_hold: float | None = None
    """Wall seconds an event is held at most, so that a quiet team is not held back (``None``:
    the window at ``clock_rate``). ``math.inf`` releases by the stamps alone: a replay whose
    thread a loaded machine stalls still comes out in the order a run sees."""
    odometry: bool = True
    ranges: bool = True
    detections: bool = True
    ground_truth: bool = False
    """Also subscribe to the robots' motion capture (:func:`~relloc.sources.zenoh_keys.truth_scopes`)
    as :class:`~relloc.events.GroundTruthEvent`: for the engine's truth sinks (a viewer's truth
    and error), never the localizers'. Its messages never wake the engine thread: they wait
    for the next that does (or the poll timeout), in arrival order."""
    subscribe_all: bool = False
    """Subscribe to ``<prefix>/**`` instead of each key (keys without a route count as
    ``unknown_key``): shows what else is published, at the cost of receiving it."""
    queue_size: int = 10000
    """Samples waiting for the engine thread; beyond that new ones are dropped (``queue_full``)."""
    own_prefix: str = ""
    """Key prefix of what this process publishes itself (the server's poses and status): with
    ``subscribe_all`` those keys come back, and are counted ``own_output``, not rejected."""


_STAMP = {0: struct.Struct(">iI"), 1: struct.Struct("<iI")}
"""The header stamp after the 4-byte CDR encapsulation header (big-, little-endian), keyed by
the header's second byte: what :func:`relloc.ros.messages.header_stamp_from_cdr` reads, inlined
in :meth:`ZenohSource._urgent` (Zenoh's threads, every message)."""


_RESTAMP_MARGIN = 0.02
"""Seconds added to the estimated stamp of a message to be restamped, when judging whether
it must wake the engine: the header clock's offset moves a little between the rule being set
and the message being handled (and a restamp never goes back), so a message near a bound
wakes the engine rather than waits."""

_FUTURE_SLACK = 0.0
"""How far (s) a stamp may lead the header clock's estimate of now and still advance the
reorder buffer (what a future stamp can move the buffer's time by)."""


class ZenohSource:
    """Subscribes to a team's topics over Zenoh and turns the messages into ordered events.

    Use :meth:`attach` with an open ``zenoh.Session``, then call :meth:`poll` in a loop on the
    engine thread; :meth:`detach` undeclares the subscribers (the session belongs to the
    caller). :meth:`handle` is the same path without Zenoh, for tests and other transports.
    """

    def __init__(self, config: TeamConfig, options: ZenohSourceOptions | None = None) -> None:
        self.config = config
        self.options = opts = options or ZenohSourceOptions()
        self.interface = opts.interface
        self.own_outputs = 0
        """Messages received on this process's own output keys (``own_prefix``)."""
        self.routes = build_routes(
            config,
            interface=opts.interface,
            prefix=opts.prefix,
            odometry=opts.odometry,
            ranges=opts.ranges,
            detections=opts.detections,
            ground_truth=opts.ground_truth,
        )
        for key, route in self.routes.items():
            missing = [t for t in route.msgtypes if not layouts(t)]
            if missing:  # cannot happen with the shipped type store; guards a broken install
                raise ConfigError(f"message type(s) {missing} of {key!r} are unknown")
        self.stats = IngestStats()
        self._dds_types = {
            key: {dds_type_name(t): t for t in route.msgtypes} for key, route in self.routes.items()
        }
        self._envelope = RmwEnvelope(self._dds_types)
        self.transport: TransportStats = self._envelope.stats
        self.clock = HeaderClock(opts.clock_rate, config.clock_offset)
        hold = opts.reorder_hold
        if hold is None:
            hold = opts.reorder_window / opts.clock_rate
        self.buffer: ReorderBuffer[Arrival] = ReorderBuffer(opts.reorder_window, hold=hold)
        self._converter = Converter(self.stats, self.clock, log, opts.interface.distro)
        # Zenoh's threads append to the inbox (a deque: appends and pops are atomic, its order
        # is the arrival order) and put a token on the wake queue when the engine thread has to
        # run (SimpleQueue: C-implemented, the cheapest hand-over between threads CPython has).
        # Both are unbounded, so the size limit is checked (approximately) before each append.
        self._inbox: deque[tuple[str, bytes, float, bytes | None]] = deque()
        self._wake: queue.SimpleQueue[None] = queue.SimpleQueue()
        self._max_queue = opts.queue_size
        self._rule: WakeRule | None = None
        # The keys a wake rule can judge before decoding (rmw_zenoh: with the type relloc
        # expects): odometry and measurements, each with its kind and whether it is restamped.
        self._judged: dict[str, tuple[bool, str, bool]] = {}
        # The keys that never wake it: motion capture (no localizer is fed it).
        self._patient: set[str] = set()
        for key, route in self.routes.items():
            wake = sensor(route.kind).wake
            patient = route.kind == GROUND_TRUTH.kind
            if wake is None and not patient:
                continue
            judged = (wake == "odometry", route.kind, route.restamped)
            for data_key in self._data_keys(key):
                if patient:
                    self._patient.add(data_key)
                else:
                    self._judged[data_key] = judged
        self._restamped_kinds = tuple(sorted({r.kind for r in self.routes.values() if r.restamped}))
        self._restamp_offset: dict[str, float] = {}
        """Per kind, the header clock's offset when the rule was set, plus ``_RESTAMP_MARGIN``:
        a restamped message's stamp, from its receive time, by an estimate a little late."""
        self._subscribers: list[Any] = []
        self._lock = threading.Lock()
        self._queue_full = 0
        self._ready: list[Arrival] = []
        """Events handled from the queue and released, not yet returned by :meth:`poll`."""

    def _data_keys(self, key: str) -> list[str]:
        """The keys a topic key's messages arrive on (rmw_zenoh: one per type and hash)."""
        if not self.interface.rmw:
            return [key]
        return [
            f"{key}/{name}/{hash_}"
            for name, msgtype in self._dds_types[key].items()
            for hash_ in (HASH_NOT_SUPPORTED, *(lay.hash for lay in layouts(msgtype)))
        ]

    # ------------------------------------------------------------------ zenoh side
    @property
    def keys(self) -> list[str]:
        """The topic keys subscribed to (sorted)."""
        return sorted(self.routes)

    @property
    def expressions(self) -> list[str]:
        """The key expressions :meth:`attach` subscribes to."""
        if self.options.subscribe_all:
            return [self.interface.everything_expr(self.options.prefix)]
        return [self.interface.subscription_expr(k) for k in self.keys]

    def attach(self, session: Any, node: ZenohNode | None = None) -> None:
        """Declare the subscribers on ``session`` (a ``zenoh.Session``); with rmw_zenoh and a
        ``node``, also the subscriptions' liveliness tokens (the node undeclares them)."""
        exprs = self.expressions
        for expr in exprs:
            self._subscribers.append(session.declare_subscriber(expr, self.on_sample))
        if node is not None and self.interface.rmw:
            scoped = route_scopes(
                self.config,
                odometry=self.options.odometry,
                ranges=self.options.ranges,
                detections=self.options.detections,
            )
            if self.options.ground_truth:
                scoped += truth_scopes(self.config)
            for route, scope in scoped:
                for msgtype in route.msgtypes:
                    channel = self.interface.channel(
                        route.topic, msgtype, prefix=self.options.prefix, scope=scope
                    )
                    node.announce_subscription(channel)
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
        """Zenoh callback (Zenoh's threads): copy, time and queue; wake the engine thread if
        the message is urgent (:meth:`rearm`); nothing else."""
        received = time.time()
        attachment = sample.attachment
        raw = attachment.to_bytes() if attachment is not None else None
        inbox = self._inbox
        if len(inbox) < self._max_queue:
            key, payload = str(sample.key_expr), sample.payload.to_bytes()
            inbox.append((key, payload, received, raw))
            # Queued first, judged after: rearm() sets the rule first, then looks at the queue.
            if self._urgent(self._rule, key, payload, received):
                self._wake.put(None)
        else:
            with self._lock:
                self._queue_full += 1
                n = self._queue_full
            if n == 1 or n % 1000 == 0:
                log.warning("engine falling behind: %d samples dropped (queue full)", n)

    def wake(self) -> None:
        """Make a blocked :meth:`poll` return now (e.g. on shutdown)."""
        self._wake.put(None)

    @property
    def queue_depth(self) -> int:
        return len(self._inbox)

    def _urgent(self, rule: WakeRule | None, key: str, payload: bytes, received: float) -> bool:
        """Whether a queued message must wake the engine thread under ``rule`` (``None``: every
        message does): its key's kind and its header stamp, read without decoding; a message
        to be restamped (zero stamps) by its receive time on the header clock as the rule was
        set, taken ``_RESTAMP_MARGIN`` late (the offset moves a little as messages come)."""
        # Runs on Zenoh's threads for every message, cold: header_stamp and WakeRule.urgent
        # written out, one Python frame instead of three.
        if rule is None:
            return True
        judged = self._judged.get(key)
        if judged is None:  # another kind, or no route (a rejection)
            return key not in self._patient
        odometry, kind, zero_stamps = judged
        t = 0.0
        if not zero_stamps and len(payload) >= 12 and payload[0] == 0 and payload[1] <= 1:
            sec, nanosec = _STAMP[payload[1]].unpack_from(payload, 4)
            t = sec + nanosec * 1e-9
        if t == 0.0:
            offset = self._restamp_offset.get(kind)
            if offset is None:
                return True
            t = offset + self.clock.rate * received
        measurement_from, odometry_from, lo, hi = rule
        return not lo <= t <= hi or t >= (odometry_from if odometry else measurement_from)

    # ------------------------------------------------------------------ engine side
    def rearm(self, rule: WakeRule | None) -> None:
        """Wake the engine thread from now on only for the messages urgent by ``rule`` (the
        consumer's :class:`~relloc.events.WakeRule` for its state after every event taken so
        far; ``None``: for every message). Any other message waits in the queue, and is handled
        with the next urgent one, in arrival order, or at the next :meth:`poll` timeout: the
        same events in the same order, without waking the engine for most messages (a thread
        woken for one message runs cold, and that cost is most of a live server's CPU). Wakes
        the engine now if a message already queued is urgent by ``rule``. Call from the engine
        thread, after feeding what :meth:`poll` returned."""
        if rule is not None:  # the offsets first: a callback may judge by the new rule now
            self._restamp_offset = {
                kind: self.clock.offset(kind) + _RESTAMP_MARGIN for kind in self._restamped_kinds
            }
        self._rule = rule
        for key, payload, received, _ in list(self._inbox):
            if self._urgent(rule, key, payload, received):
                self._wake.put(None)
                return

    def poll(self, timeout: float) -> list[Arrival]:
        """Wait up to ``timeout`` s for an urgent message (:meth:`rearm`), handle all queued
        ones, return due events.

        Returns early when the reorder buffer has an event due. Call from one thread only.
        """
        due = self.buffer.next_due()
        wait = timeout if due is None else max(0.0, min(timeout, due - time.time()))
        wake = self._wake
        if wait > 0 and wake.empty():
            with contextlib.suppress(queue.Empty):
                wake.get(timeout=wait)
        while not wake.empty():  # one consumer: empty() is exact
            wake.get_nowait()
        return self.take_queued()

    def take_queued(self) -> list[Arrival]:
        """Handle every queued message now, without waiting; return due events."""
        inbox = self._inbox
        while inbox:
            self._handle_queued(inbox.popleft())
        if self._queue_full:  # an int read needs no lock
            self._sync_queue_full()
        return self._released(self._take_ready() + self.buffer.pop_ready(time.time()))

    def drain(self) -> list[Arrival]:
        """Handle everything still queued and release everything held (shutdown)."""
        inbox = self._inbox
        while inbox:
            self._handle_queued(inbox.popleft())
        self._sync_queue_full()
        self.stats.clock_offset = self.clock.overall
        return self._released(self._take_ready() + self.buffer.flush())

    def _handle_queued(self, item: tuple[str, bytes, float, bytes | None]) -> None:
        """Handle one queued message. Without a reorder window its event leaves at once, so
        that events handled together (a burst, messages that waited) keep their arrival order."""
        self.handle(*item)
        if self.buffer.window == 0.0 and len(self.buffer):
            self._ready += self.buffer.pop_ready()

    def _take_ready(self) -> list[Arrival]:
        ready, self._ready = self._ready, []
        return ready

    def handle(
        self,
        key: str,
        payload: bytes | bytearray | memoryview,
        received: float,
        attachment: bytes | None = None,
    ) -> None:
        """Decode one message (received on the data key ``key``, with its raw Zenoh
        ``attachment``) and put its event in the reorder buffer (or count why not)."""
        topic_key, dds_type, type_hash_ = self.interface.split_key(key)
        route = self.routes.get(topic_key)
        if route is None:
            own = self.options.own_prefix.strip("/").split("/")
            parts = topic_key.strip("/").split("/")
            if own != [""] and own in (
                parts[: len(own)],
                parts[1 : 1 + len(own)],
            ):  # rmw: after the domain
                self.own_outputs += 1
                return
            self._converter.reject("unknown_key", key)
            return
        layout = None
        if self.interface.rmw:
            opened = self._envelope.open(
                topic_key, dds_type, type_hash_, attachment, self._converter.reject
            )
            if opened is None:
                return
            sent, layout = opened
        else:
            sent = decode_sent_time(attachment)
        for event in self._converter.events(route, topic_key, payload, received, layout):
            self.buffer.push(event.t, Arrival(event, topic_key, received, sent), received)
            # The buffer's time advances with the stamps, but never past the header clock's now
            # (plus a slack): one message stamped in the future must not release everything
            # held, and make every later message late, for the rest of the run.
            t = event.t
            if self.buffer.window > 0.0:
                t = min(
                    t, self.clock.offset(route.kind) + self.clock.rate * received + _FUTURE_SLACK
                )
            self.buffer.advance(t)

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
