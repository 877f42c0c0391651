"""One ingestion layer: a team's ROS 2 messages become relloc events, whatever carried them.

A rosbag2 file and a Zenoh subscription deliver the same thing, CDR-serialised ROS 2 messages
with their arrival times, so everything from those bytes to an ordered stream of
:mod:`relloc.events` lives here once; a source keeps only its transport
(:mod:`relloc.sources.rosbag`, :mod:`relloc.sources.zenoh_source`).

* :func:`team_routes` reads the :class:`~relloc.config.TeamConfig` once and says, per topic,
  what its messages become (a :class:`~relloc.sensors.Route`); :func:`match_range_topics`
  lists a bag's range topics.
* :class:`Converter` decodes, stamps (all-zero header stamps are restamped on the header
  clock, :mod:`relloc.sources.clock`) and has the route's sensor build the event.
* What cannot be used is dropped and counted per reason in :class:`IngestStats`, so that
  downstream stages only ever see valid numbers.

Routes, zero stamps and the rejection reasons in full: ``docs/explanation/internals.md``.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from relloc.config import TeamConfig
from relloc.events import Event
from relloc.ros.distros import DEFAULT_DISTRO, Layout, layouts
from relloc.ros.messages import MessageDecodeError, decode, stamp_to_sec
from relloc.sensors import Route, Sensor, check_config, kind_of, registered, sensor
from relloc.sensors.builtin import match_range_topics
from relloc.sources.clock import HeaderClock

__all__ = [
    "Converter",
    "IngestStats",
    "event_kind",
    "match_range_topics",
    "switched_on",
    "team_routes",
]

RESTAMP_STEP = 1e-6
"""Smallest step (s) between two restamped times of one topic."""


# ---------------------------------------------------------------------------- routes
def team_routes(
    config: TeamConfig,
    *,
    odometry: bool = True,
    ranges: bool = True,
    detections: bool = True,
    ground_truth: bool = False,
    objects: Sequence[str] = (),
) -> list[Route]:
    """Every topic the team's data comes on, with its :class:`~relloc.sensors.Route`: each
    robot's own topics (per robot, sensors in registration order), then the other routes of
    each sensor and the extra motion-capture ``objects`` (the built-ins: sightings, objects,
    UWB pairs).

    The switches leave the sensors under them out (:attr:`~relloc.sensors.Sensor.switch`).
    Raises :class:`~relloc.config.ConfigError` for a config a sensor rejects (a range-topic
    template without ``{a}`` and ``{b}``, a ``sensors`` table of no registered sensor).
    """
    check_config(config)
    chosen = switched_on(
        odometry=odometry, ranges=ranges, detections=detections, ground_truth=ground_truth
    )
    routes: list[Route] = []
    for robot in config.robots:
        for s in chosen:
            routes += s.robot_routes(config, robot)
    for s in registered():
        if s in chosen:
            routes += s.team_routes(config)
        routes += s.object_routes(config, objects)
    return routes


def switched_on(
    *, odometry: bool, ranges: bool, detections: bool, ground_truth: bool
) -> list[Sensor]:
    """The registered sensors the source switches leave in, in registration order."""
    on = {
        "odometry": odometry,
        "ranges": ranges,
        "detections": detections,
        "ground_truth": ground_truth,
    }
    return [s for s in registered() if s.switch is None or on[s.switch]]


# ---------------------------------------------------------------------------- stats
@dataclass
class IngestStats:
    """What a source read, emitted and rejected: one record for every source.

    Messages are counted per *stream*: the topic for a bag, the key expression for Zenoh.
    """

    messages: Counter[str] = field(default_factory=Counter)
    """Messages per stream (only streams with a route)."""
    events: Counter[str] = field(default_factory=Counter)
    """Events emitted per sensor kind (:func:`event_kind`): ``odometry``, ``range``..."""
    rejected: Counter[str] = field(default_factory=Counter)
    """Dropped messages or values by reason (``decode_error``, ``range_nonfinite``, ``late``...)."""
    restamped: Counter[str] = field(default_factory=Counter)
    """Messages per stream stamped from their receive time (zero stamps, ``odom_zero_stamps``)."""
    repeated_ranges: int = 0
    """Ranges equal to the previous value of the same topic (passed on)."""
    layouts: Counter[str] = field(default_factory=Counter)
    """Messages per layout they were decoded in (``sensor_msgs/msg/Range@humble``), for types
    whose definition differs between ROS 2 distributions."""
    out_of_order: int = 0
    """Events released after a later-stamped one and passed on (live; a bag drops them as
    ``rejected["late"]``)."""
    clock_offset: float = 0.0
    """Header stamp minus receive time (s) over all topics (a bag: estimated before streaming;
    live: the estimate when the source was drained)."""
    last_received: dict[str, float] = field(default_factory=dict)
    """Per robot, the receive time of its last message (any kind): who went quiet."""

    def emitted(self, event: Event) -> None:
        """Count an event leaving the source."""
        self.events[kind_of(event)] += 1

    def as_dict(self) -> dict[str, Any]:
        """Plain-dict view for ``--json`` output and the live status."""
        return {
            "messages": dict(self.messages),
            "events": dict(self.events),
            "rejected": dict(self.rejected),
            "restamped": dict(self.restamped),
            "repeated_ranges": self.repeated_ranges,
            "layouts": dict(self.layouts),
            "out_of_order": self.out_of_order,
            "clock_offset": self.clock_offset,
        }


def event_kind(event: Event) -> str:
    """The kind name of an event: its sensor's (``"odometry"``...), else its class name."""
    return kind_of(event)


# ---------------------------------------------------------------------------- conversion
class Converter:
    """Turns one message of a :class:`Route` into its event: decode, stamp, check, count.

    Counts into ``stats``; restamps with ``clock`` (and teaches it the stamped messages).
    ``log``, if given, gets a warning for the first rejection of each reason and every 1000th
    (a live server's operator wants to hear; an offline run reports the counts at the end).
    One converter per pass over the data: it remembers each topic's restamped time and what the
    sensors keep in :meth:`memory` (each topic's previous range). It is the
    :class:`~relloc.sensors.Conversion` the sensors convert with.
    """

    def __init__(
        self,
        stats: IngestStats,
        clock: HeaderClock,
        log: logging.Logger | None = None,
        distro: str = DEFAULT_DISTRO,
    ) -> None:
        self.stats = stats
        self.clock = clock
        self.log = log
        self.distro = distro
        """The distribution whose layout is tried first where a type has several."""
        self._memory: dict[str, dict[Any, Any]] = {}
        self._last_restamp: dict[str, float] = {}
        self._layouts: dict[str, tuple[Layout, ...]] = {}

    def convert(
        self,
        route: Route,
        stream: str,
        payload: bytes | bytearray | memoryview,
        received: float,
        layout: Layout | None = None,
    ) -> Event | None:
        """The one event of a message of a sensor that makes one per message (:meth:`events`),
        or ``None``; a message that made several is a ``ValueError``."""
        events = self.events(route, stream, payload, received, layout)
        if len(events) > 1:
            raise ValueError(
                f"a message on {stream!r} made {len(events)} events: use Converter.events"
            )
        return events[0] if events else None

    def events(
        self,
        route: Route,
        stream: str,
        payload: bytes | bytearray | memoryview,
        received: float,
        layout: Layout | None = None,
    ) -> list[Event]:
        """The events of one ``payload`` on ``stream`` (a topic or key routed by ``route``),
        received at ``received``, decoded in ``layout`` (else in each known layout of the
        route's types in turn): one for most sensors, one per peer of a range type listing
        peers, none (counted) if the message is unusable."""
        stats = self.stats
        stats.messages[stream] += 1
        stats.last_received[route.robot] = received
        if route.robot_b:
            stats.last_received[route.robot_b] = received
        if not isinstance(payload, bytes):
            payload = bytes(payload)  # the decoders hash and slice it
        own = sensor(route.kind)
        tried = (layout,) if layout is not None else self._candidates(route, stream)
        fast = None
        for lay in tried:
            fast = own.fast(payload, lay)
            if fast is not None:
                stats.layouts[str(lay)] += 1
                break
        msg = None
        if fast is None:
            msg = self._decode(tried, stream, payload)
            if msg is None:
                return []
            stamp = (
                0.0 if route.restamped else stamp_to_sec(msg.header.stamp)
            )  # a type may have no header
        else:
            stamp = fast[0]
        if route.restamped or stamp == 0.0:
            stamp = self._restamp(route, stream, received)
        else:
            self.clock.observe(stream, route.kind, stamp, received)
        out = own.convert(route, stream, msg, fast, stamp, self)
        if out is None:
            return []
        return out if isinstance(out, list) else [out]

    def memory(self, kind: str) -> dict[Any, Any]:
        """State the sensor ``kind`` keeps for this pass (a range's previous value per topic)."""
        found = self._memory.get(kind)
        if found is None:
            found = self._memory[kind] = {}
        return found

    def reject(self, reason: str, stream: str, detail: str = "") -> None:
        """Count (and maybe log) a message dropped for ``reason``."""
        self.stats.rejected[reason] += 1
        if self.log is not None:
            n = self.stats.rejected[reason]
            if n == 1 or n % 1000 == 0:
                self.log.warning(
                    "rejected a message on %r (%s, %d so far) %s", stream, reason, n, detail
                )

    def _candidates(self, route: Route, stream: str) -> tuple[Layout, ...]:
        """The layouts a message of ``route`` may be in, this converter's distribution first."""
        found = self._layouts.get(stream)
        if found is None:
            found = self._layouts[stream] = tuple(
                lay for msgtype in route.msgtypes for lay in layouts(msgtype, self.distro)
            )
        return found

    def _decode(self, tried: tuple[Layout, ...], stream: str, payload: bytes) -> Any:
        error: MessageDecodeError | None = None
        for lay in tried:
            try:
                msg = decode(payload, lay.msgtype, lay)
            except MessageDecodeError as exc:
                error = exc
                continue
            self.stats.layouts[str(lay)] += 1
            return msg
        self.reject("decode_error", stream, str(error) if error else "no known layout")
        return None

    def _restamp(self, route: Route, stream: str, received: float) -> float:
        previous = self._last_restamp.get(stream, -math.inf)
        stamp = max(self.clock.stamp(route.kind, received), previous + RESTAMP_STEP)
        self._last_restamp[stream] = stamp
        self.stats.restamped[stream] += 1
        return stamp
