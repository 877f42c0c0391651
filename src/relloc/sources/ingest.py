"""One ingestion layer: a team's ROS 2 messages become relloc events, whatever carried them.

A rosbag2 file and a Zenoh subscription deliver the same thing: ROS 2 messages serialised as
CDR, each with the time it arrived. Everything between those bytes and an ordered stream of
:mod:`relloc.events` is the same for both, and lives here; a source keeps only its transport
(:mod:`relloc.sources.rosbag` reads a bag with ``rosbags``, :mod:`relloc.sources.zenoh_source`
subscribes and hands payloads from Zenoh's threads to the engine's).

Routes from the team config
---------------------------
:func:`team_routes` reads the :class:`~relloc.config.TeamConfig` once and says, per topic,
what its messages become: each robot's ``odom_topic`` -> :class:`~relloc.events.OdometryEvent`;
``uwb.range_topic`` with ``{a}``/``{b}`` = node ids, for every pair of the team's robots and in
both node orders (a UWB driver may publish either) -> ``RangeEvent`` carrying both robots and
both nodes; each robot's ``detection_topic`` -> ``DetectionEvent`` in the body frame (with the
robot's camera extrinsics); ``mocap_topic`` with ``{body}`` = a robot's ``mocap_body`` (or an
extra object's name) -> ``GroundTruthEvent``. A :class:`Route` is what one topic needs to be
converted; a source maps its own names onto routes (a bag keeps the routes whose topic it
holds; Zenoh puts each route on the key expressions of the bridge convention).

Header stamps and receive time
------------------------------
Events carry **header stamps**: the time the sensor captured the data, on one clock for the
whole team. The time a message *arrived* is later, by a lag that depends on the kind of
message (detections wait for the image pipeline, odometry for its own loop), so messages of
different topics arrive out of header order. Receive time is used only where no stamp exists.

:class:`HeaderClock` puts a receive time on the header clock: ``header = offset(kind) + rate *
receive``, where the offset of a kind of message is the median, over the topics of that kind,
of each topic's median of ``stamp - rate * receive`` (kinds are kept apart so that a restamped
odometry message keeps odometry's lag; a kind never seen stamped uses the median over all
topics; with nothing seen at all the offset is 0, which is right live: ROS stamps wall time).
``rate`` is header seconds per receive second (a recording replayed twice as fast: 2).

The two clocks need not be close. A recording that was re-recorded from a replay has receive
times from the day of the replay and header stamps from the day of the experiment (the
shortbag's differ by weeks: ``docs/results.md``), but the offset between them is constant over
the recording. A bag source can therefore estimate it once, from the header stamps at the start
of the bag, and :meth:`HeaderClock.freeze` it; a live source cannot look ahead and learns it as
messages come (a running median over each topic's last ``window`` stamped messages).
``TeamConfig.clock_offset`` fixes the offset instead of estimating it.

Zero stamps
-----------
Some drivers publish all-zero header stamps (the shortbag's ``/cali/turtle05/odom``), and
a robot can be flagged ``odom_zero_stamps`` when its odometry stamps are not to be trusted.
:class:`Converter` gives such a message ``HeaderClock.stamp(kind, receive time)`` and counts it
in ``restamped``; successive restamped times of one topic always increase (arrival order is the
topic's order, even while a live estimate of the offset moves).

Conversion and rejections
-------------------------
:meth:`Converter.convert` decodes one payload (odometry and ranges through the fast fixed-layout
path of :mod:`relloc.ros.cdr`, everything else or anything odd through ``rosbags``), stamps it
and builds its event. What cannot be used is dropped and counted per reason in the
:class:`IngestStats` record, so that downstream stages only ever see valid numbers:
``decode_error``, ``range_nonfinite``/``range_nonpositive`` and, per object,
``detection_zero_position``/``detection_nonfinite``/``detection_behind_camera``. A detection
frame with no valid object is still an event ("the camera saw nothing then"). A range equal to
the previous one of its topic (a UWB driver republishing its last value) passes and is counted
in ``repeated_ranges``; the localizer decides about it.

Reorder window
--------------
:class:`ReorderBuffer` restores header order within a bounded window: it holds events in a heap
and releases, in stamp order, those ``window`` seconds of header time behind the newest time the
source knows has arrived (live: the newest stamp; a bag: the newest receive time put on the
header clock, since a message received later is stamped earlier only by its lag), or that have
waited ``hold`` seconds (live, so that a quiet team is not held back). Memory stays bounded by a
window's worth of messages. An event older than one already released cannot be put in order
any more: it is counted (``late``) and either passed on at once (live: the localizer judges
whether it is too late) or dropped (a bag: an offline run sees strictly ordered events). The
window is latency: live, every event waits up to that long.
"""

from __future__ import annotations

import heapq
import logging
import math
import re
import statistics
from collections import Counter, deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any, Generic, Literal, TypeVar

from relloc.config import CameraConfig, ConfigError, TeamConfig
from relloc.events import DetectionEvent, Event, GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.ros.cdr import decode_odometry, decode_range
from relloc.ros.messages import (
    ODOMETRY,
    POINT_STAMPED,
    POSE_ARRAY,
    POSE_STAMPED,
    RANGE,
    SPATIAL_DETECTION_ARRAY,
    MessageDecodeError,
    decode,
    detections_to_event,
    odometry_to_event,
    point_to_sighting,
    pose_to_ground_truth,
    range_rejection,
    stamp_to_sec,
)

__all__ = [
    "DETECTION_TYPES",
    "Converter",
    "HeaderClock",
    "IngestStats",
    "Kind",
    "ReorderBuffer",
    "Route",
    "event_kind",
    "match_range_topics",
    "sighting_routes",
    "team_routes",
]

Kind = Literal["odometry", "range", "detection", "ground_truth", "sighting"]

DETECTION_TYPES: dict[str, tuple[str, ...]] = {
    "depthai": (SPATIAL_DETECTION_ARRAY,),
    "posearray": (POSE_ARRAY,),
    "": (SPATIAL_DETECTION_ARRAY, POSE_ARRAY),
}
"""Message types a robot's ``detection_format`` accepts (unspecified: both, tried in order)."""

RESTAMP_STEP = 1e-6
"""Smallest step (s) between two restamped times of one topic."""


# ---------------------------------------------------------------------------- routes
@dataclass(frozen=True)
class Route:
    """How the messages of one topic become events."""

    topic: str
    kind: Kind
    msgtypes: tuple[str, ...]
    """Message types tried in order (an unspecified detection format accepts two)."""
    robot: str
    """The robot (or motion-capture object) the events concern; a range's first robot."""
    what: str
    """What the topic is, for messages: ``"odometry of r1"``, ``"UWB ranges n_1-n_2"``..."""
    robot_b: str = ""
    node_a: str = ""
    node_b: str = ""
    camera: CameraConfig | None = None
    zero_stamps: bool = False
    """Stamp every message from its receive time (``odom_zero_stamps``)."""
    sigma: tuple[float, float] = (0.0, 0.0)
    """A sighting's range (m) and bearing (rad) noise."""


def _check_range_template(template: str) -> None:
    if "{a}" not in template or "{b}" not in template:
        raise ConfigError(f"uwb.range_topic {template!r} must contain both {{a}} and {{b}}")


def team_routes(
    config: TeamConfig,
    *,
    odometry: bool = True,
    ranges: bool = True,
    detections: bool = True,
    ground_truth: bool = False,
    objects: Sequence[str] = (),
) -> list[Route]:
    """Every topic the team's data comes on, with its :class:`Route`, per robot (odometry,
    motion capture, detections), then the extra motion-capture ``objects``, then the UWB pairs.

    The switches leave kinds out. Raises :class:`~relloc.config.ConfigError` for a range-topic
    template without ``{a}`` and ``{b}``.
    """
    routes: list[Route] = []
    for robot in config.robots:
        if odometry and robot.odom_topic:
            routes.append(
                Route(
                    robot.odom_topic,
                    "odometry",
                    (ODOMETRY,),
                    robot.name,
                    f"odometry of {robot.name}",
                    zero_stamps=robot.odom_zero_stamps,
                )
            )
        if ground_truth and robot.mocap_body:
            topic = config.mocap_topic.format(body=robot.mocap_body)
            what = f"motion capture of {robot.name}"
            routes.append(Route(topic, "ground_truth", (POSE_STAMPED,), robot.name, what))
        if detections and robot.detection_topic:
            fmt = robot.detection_format
            routes.append(
                Route(
                    robot.detection_topic,
                    "detection",
                    DETECTION_TYPES[fmt],
                    robot.name,
                    f"detections of {robot.name} ({fmt or 'any'})",
                    camera=robot.camera,
                )
            )
    if detections:  # the teammates each robot sees: one topic per ordered pair
        routes += sighting_routes(config)
    for body in objects:
        topic = config.mocap_topic.format(body=body)
        what = f"motion capture of object {body}"
        routes.append(Route(topic, "ground_truth", (POSE_STAMPED,), body, what))
    if ranges:
        template = config.uwb.range_topic
        _check_range_template(template)
        with_nodes = [r for r in config.robots if r.uwb_node]
        for ra, rb in combinations(with_nodes, 2):
            if ra.uwb_node == rb.uwb_node:
                continue
            for first, second in ((ra, rb), (rb, ra)):
                routes.append(
                    Route(
                        template.format(a=first.uwb_node, b=second.uwb_node),
                        "range",
                        (RANGE,),
                        first.name,
                        f"UWB ranges {first.uwb_node}-{second.uwb_node}",
                        robot_b=second.name,
                        node_a=first.uwb_node,
                        node_b=second.uwb_node,
                    )
                )
    return routes


def sighting_routes(config: TeamConfig) -> list[Route]:
    """Per observer with a ``sighting_topic`` template and per teammate, the route of its
    ``geometry_msgs/PointStamped`` sightings (a pair without a topic has none)."""
    routes = []
    for robot in config.robots:
        if not robot.sighting_topic:
            continue
        if "{target}" not in robot.sighting_topic:
            raise ConfigError(f"{robot.name}: sighting_topic {robot.sighting_topic!r} must contain {{target}}")
        sigma = (robot.sighting_sigma_range, math.radians(robot.sighting_sigma_bearing_deg))
        for other in config.robots:
            if other.name != robot.name:
                topic = robot.sighting_topic.format(target=other.name)
                what = f"sightings of {other.name} by {robot.name}"
                routes.append(Route(topic, "sighting", (POINT_STAMPED,), robot.name, what, robot_b=other.name, sigma=sigma))
    return routes


def match_range_topics(topics: Iterable[str], template: str) -> dict[str, tuple[str, str]]:
    """The topics matching a UWB range-topic template, any nodes (static anchors too):
    topic -> (node a, node b), sorted by topic.

    Raises :class:`~relloc.config.ConfigError` for a template without ``{a}`` and ``{b}``.
    """
    _check_range_template(template)
    parts = re.split(r"(\{a\}|\{b\})", template)
    pattern = "".join(f"(?P<{p[1]}>[^/]+)" if p in ("{a}", "{b}") else re.escape(p) for p in parts)
    regex = re.compile(f"^{pattern}$")
    out: dict[str, tuple[str, str]] = {}
    for topic in sorted(topics):
        match = regex.match(topic)
        if match is not None:
            out[topic] = (match.group("a"), match.group("b"))
    return out


# ---------------------------------------------------------------------------- stats
@dataclass
class IngestStats:
    """What a source read, emitted and rejected: one record for every source.

    Messages are counted per *stream*: the topic for a bag, the key expression for Zenoh.
    """

    messages: Counter[str] = field(default_factory=Counter)
    """Messages per stream (only streams with a route)."""
    events: Counter[str] = field(default_factory=Counter)
    """Events emitted per kind: ``odometry``, ``range``, ``detection``, ``ground_truth``."""
    rejected: Counter[str] = field(default_factory=Counter)
    """Dropped messages or values by reason (``decode_error``, ``range_nonfinite``, ``late``...)."""
    restamped: Counter[str] = field(default_factory=Counter)
    """Messages per stream stamped from their receive time (zero stamps, ``odom_zero_stamps``)."""
    repeated_ranges: int = 0
    """Ranges equal to the previous value of the same topic (passed on)."""
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
        self.events[_KIND_OF_TYPE.get(type(event)) or type(event).__name__] += 1

    def as_dict(self) -> dict[str, Any]:
        """Plain-dict view for ``--json`` output and the live status."""
        return {
            "messages": dict(self.messages),
            "events": dict(self.events),
            "rejected": dict(self.rejected),
            "restamped": dict(self.restamped),
            "repeated_ranges": self.repeated_ranges,
            "out_of_order": self.out_of_order,
            "clock_offset": self.clock_offset,
        }


_KIND_OF_TYPE: dict[type, str] = {
    OdometryEvent: "odometry",
    RangeEvent: "range",
    DetectionEvent: "detection",
    GroundTruthEvent: "ground_truth",
}


def event_kind(event: Event) -> str:
    """The kind name of an event (``"odometry"``...; another type: its class name)."""
    return _KIND_OF_TYPE.get(type(event), type(event).__name__)


# ---------------------------------------------------------------------------- clock
class HeaderClock:
    """Puts receive times on the header clock: ``header = offset(kind) + rate * receive``.

    :meth:`observe` learns from the header stamps of one *stream* (a topic or a key) of a kind;
    zero stamps are counted, not learned from. Each stream keeps its last ``window`` offsets
    ``stamp - rate * receive``; the offset of a kind is the median of its streams' medians (a
    kind never seen stamped: the median over all streams; nothing seen: 0).
    ``fixed_offset`` overrides every estimate. After :meth:`freeze` observations are ignored and
    the offsets stay as they are (a recording's clock offset is constant).
    """

    def __init__(
        self, rate: float = 1.0, fixed_offset: float | None = None, window: int = 200
    ) -> None:
        if not rate > 0:
            raise ValueError(f"clock rate must be positive, got {rate}")
        self.rate = float(rate)
        self.fixed_offset = fixed_offset
        self.frozen = False
        self._window = window
        self._samples: dict[str, deque[float]] = {}
        self._of_kind: dict[str, list[str]] = {}
        self._zeros: Counter[str] = Counter()
        self._medians: dict[str, float] = {}
        self._stale: set[str] = set()

    def observe(self, stream: str, kind: str, stamp: float, received: float) -> None:
        """Learn from a message of ``stream`` (of ``kind``) stamped ``stamp``, received then."""
        if self.frozen:
            return
        if stamp == 0.0:
            self._zeros[stream] += 1
            return
        samples = self._samples.get(stream)
        if samples is None:
            samples = self._samples[stream] = deque(maxlen=self._window)
            self._of_kind.setdefault(kind, []).append(stream)
        samples.append(stamp - self.rate * received)
        self._stale.add(stream)

    def freeze(self) -> None:
        """Stop learning: the offsets stay those estimated so far."""
        self.frozen = True

    def seen(self, stream: str) -> int:
        """Messages of ``stream`` observed and kept (stamped or zero)."""
        samples = self._samples.get(stream)
        return (len(samples) if samples else 0) + self._zeros[stream]

    @property
    def zero_stamp_streams(self) -> set[str]:
        """Streams observed with zero stamps only."""
        return {s for s, n in self._zeros.items() if n and s not in self._samples}

    @property
    def zeros_seen(self) -> bool:
        """Whether any zero stamp was observed."""
        return bool(self._zeros)

    def stream_offsets(self) -> dict[str, float]:
        """Median ``stamp - rate * receive`` per stream, in the order the streams were first
        observed stamped."""
        return {s: self._median(s) for s in self._samples}

    def offset(self, kind: str) -> float:
        """Current estimate of ``header - rate * receive`` for messages of ``kind``."""
        if self.fixed_offset is not None:
            return self.fixed_offset
        own = self._of_kind.get(kind)
        if own:
            return statistics.median([self._median(s) for s in own])
        return self.overall

    @property
    def overall(self) -> float:
        """Offset over all streams (the fixed one, if set; 0 with nothing seen)."""
        if self.fixed_offset is not None:
            return self.fixed_offset
        medians = self.stream_offsets()
        return statistics.median(medians.values()) if medians else 0.0

    def stamp(self, kind: str, received: float) -> float:
        """Header-clock time of a message of ``kind`` received at ``received``."""
        return self.offset(kind) + self.rate * received

    def _median(self, stream: str) -> float:
        """The stream's median offset, recomputed only after new observations."""
        if stream in self._stale:
            self._medians[stream] = statistics.median(self._samples[stream])
            self._stale.discard(stream)
        return self._medians[stream]


# ---------------------------------------------------------------------------- reorder buffer
T = TypeVar("T")


class ReorderBuffer(Generic[T]):
    """Releases items in header-stamp order after holding each for at most a window.

    The source :meth:`push`-es each item with its stamp (and receive time) and :meth:`advance`-s
    the buffer to the newest header time it knows has arrived. An item leaves once that time is
    ``window`` past its stamp, or once it has waited ``hold`` (receive-clock seconds), and in
    stamp order (ties in push order). One older than an item already released is *late*: it
    leaves at once, counted in :attr:`late`, and is returned, or dropped with ``drop_late``.
    ``window=0`` passes every item straight through.
    """

    def __init__(self, window: float, *, hold: float = math.inf, drop_late: bool = False) -> None:
        if window < 0:
            raise ValueError(f"reorder window must be >= 0, got {window}")
        self.window = float(window)
        self.hold = float(hold)
        self.drop_late = drop_late
        self._heap: list[tuple[float, int, float, T]] = []
        self._seq = 0
        self._newest = -math.inf
        self.last_released = -math.inf
        """Stamp of the newest item released so far."""
        self.late = 0
        """Items that came out after a later-stamped one (returned, or dropped)."""
        self.max_depth = 0
        """Most items held at once."""

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, t: float, item: T, received: float = 0.0) -> None:
        """Hold ``item`` stamped ``t``, received at ``received``."""
        heapq.heappush(self._heap, (t, self._seq, received, item))
        self._seq += 1
        if len(self._heap) > self.max_depth:
            self.max_depth = len(self._heap)

    def advance(self, t: float) -> None:
        """Header time ``t`` has been reached (the newest stamp, or receive time on the header
        clock)."""
        if t > self._newest:
            self._newest = t

    def pop_ready(self, now: float = -math.inf) -> list[T]:
        """Items due at receive time ``now``, in stamp order."""
        out: list[T] = []
        horizon = self._newest - self.window
        heap = self._heap
        while heap:
            t, _, received, _ = heap[0]
            late = t < self.last_released  # order is lost already: holding it cannot help
            if not late and t > horizon and now - received < self.hold:
                break
            self._release(heapq.heappop(heap), out)
        return out

    def flush(self) -> list[T]:
        """Everything held, in stamp order (end of a recording, shutdown)."""
        out: list[T] = []
        while self._heap:
            self._release(heapq.heappop(self._heap), out)
        return out

    def next_due(self) -> float | None:
        """Receive time at which the oldest held item is released by waiting, or ``None``."""
        return self._heap[0][2] + self.hold if self._heap else None

    def _release(self, entry: tuple[float, int, float, T], out: list[T]) -> None:
        t = entry[0]
        if t < self.last_released:
            self.late += 1
            if self.drop_late:
                return
        else:
            # Never past the buffer's own time: an item stamped ahead of it (a future stamp
            # let out by ``hold``) must not make every later item late.
            self.last_released = max(self.last_released, min(t, self._newest))
        out.append(entry[3])


# ---------------------------------------------------------------------------- conversion
class Converter:
    """Turns one message of a :class:`Route` into its event: decode, stamp, check, count.

    Counts into ``stats``; restamps with ``clock`` (and teaches it the stamped messages).
    ``log``, if given, gets a warning for the first rejection of each reason and every 1000th
    (a live server's operator wants to hear; an offline run reports the counts at the end).
    One converter per pass over the data: it remembers each topic's previous range and
    restamped time.
    """

    def __init__(
        self, stats: IngestStats, clock: HeaderClock, log: logging.Logger | None = None
    ) -> None:
        self.stats = stats
        self.clock = clock
        self.log = log
        self._last_range: dict[str, float] = {}
        self._last_restamp: dict[str, float] = {}

    def convert(
        self,
        route: Route,
        stream: str,
        payload: bytes | bytearray | memoryview,
        received: float,
    ) -> Event | None:
        """The event of one ``payload`` on ``stream`` (a topic or key routed by ``route``),
        received at ``received``; ``None`` (counted) if the message is unusable."""
        stats = self.stats
        stats.messages[stream] += 1
        stats.last_received[route.robot] = received
        if route.robot_b:
            stats.last_received[route.robot_b] = received
        if not isinstance(payload, bytes):
            payload = bytes(payload)  # the decoders hash and slice it
        fast = _fast_fields(route, payload)
        msg = None
        if fast is None:
            msg = self._decode(route, stream, payload)
            if msg is None:
                return None
            stamp = stamp_to_sec(msg.header.stamp)
        else:
            stamp = fast[0]
        if route.zero_stamps or stamp == 0.0:
            stamp = self._restamp(route, stream, received)
        else:
            self.clock.observe(stream, route.kind, stamp, received)
        kind = route.kind
        if kind == "odometry":
            if fast is not None:
                _, x, y, yaw, v, w = fast
                return OdometryEvent(t=stamp, robot=route.robot, x=x, y=y, yaw=yaw, v=v, w=w)
            return odometry_to_event(msg, route.robot, t=stamp)
        if kind == "range":
            distance = fast[1] if fast is not None else float(msg.range)
            reason = range_rejection(distance)
            if reason is not None:
                self.reject(f"range_{reason}", stream)
                return None
            if self._last_range.get(route.topic) == distance:
                stats.repeated_ranges += 1
            self._last_range[route.topic] = distance
            return RangeEvent(
                t=stamp,
                robot_a=route.robot,
                robot_b=route.robot_b,
                distance=distance,
                node_a=route.node_a,
                node_b=route.node_b,
            )
        if kind == "ground_truth":
            return pose_to_ground_truth(msg, route.robot, t=stamp)
        if kind == "sighting":
            return point_to_sighting(msg, route.robot, route.robot_b, *route.sigma, t=stamp)
        assert route.camera is not None
        det, rejected = detections_to_event(msg, route.robot, route.camera, t=stamp)
        for reason, n in rejected.items():
            stats.rejected[f"detection_{reason}"] += n
        return det

    def reject(self, reason: str, stream: str, detail: str = "") -> None:
        """Count (and maybe log) a message dropped for ``reason``."""
        self.stats.rejected[reason] += 1
        if self.log is not None:
            n = self.stats.rejected[reason]
            if n == 1 or n % 1000 == 0:
                self.log.warning(
                    "rejected a message on %r (%s, %d so far) %s", stream, reason, n, detail
                )

    def _decode(self, route: Route, stream: str, payload: bytes) -> Any:
        error: MessageDecodeError | None = None
        for msgtype in route.msgtypes:
            try:
                return decode(payload, msgtype)
            except MessageDecodeError as exc:
                error = exc
        self.reject("decode_error", stream, str(error))
        return None

    def _restamp(self, route: Route, stream: str, received: float) -> float:
        previous = self._last_restamp.get(stream, -math.inf)
        stamp = max(self.clock.stamp(route.kind, received), previous + RESTAMP_STEP)
        self._last_restamp[stream] = stamp
        self.stats.restamped[stream] += 1
        return stamp


def _fast_fields(route: Route, payload: bytes) -> tuple[float, ...] | None:
    """The hot messages' fields straight from the bytes (:mod:`relloc.ros.cdr`), or ``None``:
    then the full ``rosbags`` decoder decodes the payload or says why not."""
    if route.kind == "odometry":
        return decode_odometry(payload)
    if route.kind == "range":
        return decode_range(payload)
    return None
