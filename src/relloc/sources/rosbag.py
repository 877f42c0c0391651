"""rosbag2 recordings (sqlite3 or MCAP) as a time-ordered stream of relloc events.

:class:`RosbagSource` reads a bag with ``rosbags`` (no ROS installation needed) and yields the
events of one team, described by its :class:`~relloc.config.TeamConfig`:

* odometry from each robot's ``odom_topic`` -> :class:`~relloc.events.OdometryEvent`;
* UWB ranges from every topic matching ``uwb.range_topic`` (``{a}``/``{b}`` are node ids, in
  either order) whose two nodes are carried by robots of the team -> ``RangeEvent``; topics
  involving other nodes (static anchors) are ignored: the method is infrastructure-free;
* motion capture from ``mocap_topic`` with ``{body}`` = each robot's ``mocap_body`` ->
  ``GroundTruthEvent`` (optional: ``ground_truth=False``);
* spatial detections from ``detection_topic`` (``depthai`` or ``posearray`` format), moved into
  the robot body frame with the camera extrinsics -> ``DetectionEvent`` (``detections=False``).

Time
----
Events carry **header stamps** (the sensor's capture time), which lag the bag's receive time by
up to about 0.3 s (detections) and arrive out of order across topics. The source therefore keeps
a bounded reorder buffer: a heap of pending events, released once the newest receive time (put
on the header clock) has moved ``max_lag`` seconds past them. Memory stays bounded by
``max_lag`` worth of messages; the bag is streamed, never loaded whole. An event that would come
out of order anyway (a message more than ``max_lag`` late) is dropped and counted as ``late``.

Header clocks and receive clocks need not agree: the 2022-10 recordings were re-recorded from a
replay, so every header stamp is 48 days behind its receive time. Before streaming, the source
looks at the header stamps of the first seconds of the bag (12 bytes per message, no decoding)
and estimates the offset ``header - receive`` per kind of topic. A message whose header stamp is
all zeros (the shortbag's ``/cali/turtle05/odom``) gets ``receive time + offset`` of its kind,
as do all messages of a robot flagged ``odom_zero_stamps``. ``TeamConfig.clock_offset``
overrides the estimate.

Rejections
----------
Unusable values are dropped here and counted in :attr:`RosbagSource.stats` (``rejected``), so
downstream stages only ever see valid numbers: non-finite or non-positive ranges
(``range_nonfinite``, ``range_nonpositive``), detections with an all-zero (no depth),
non-finite or behind-the-camera position (``detection_zero_position``, ...), undecodable
messages (``decode_error``) and ``late`` events. Detection frames with no valid object are still
emitted (with no objects): "the camera saw nothing" at that time. Exact repeats of the previous
range of a pair (the UWB driver republishes its last value) are passed through and counted in
``stats.repeated_ranges``.

Errors
------
Everything the user can get wrong (path missing, not a bag, corrupted or truncated database, a
configured topic absent, a wrong message type) raises :class:`BagError` with a one-line
explanation (the missing-topic message lists the bag's topics).
"""

from __future__ import annotations

import heapq
import math
import re
import statistics
from collections import Counter, defaultdict
from collections.abc import Collection, Iterable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from rosbags.rosbag2 import Reader

from relloc.config import CameraConfig, TeamConfig
from relloc.events import DetectionEvent, Event, GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.ros.messages import (
    ODOMETRY,
    POSE_ARRAY,
    POSE_STAMPED,
    RANGE,
    SPATIAL_DETECTION_ARRAY,
    MessageDecodeError,
    decode,
    detections_to_event,
    header_stamp_from_cdr,
    odometry_to_event,
    pose_to_ground_truth,
    range_rejection,
    range_to_event,
    stamp_to_sec,
    typestore,
)

__all__ = [
    "BagError",
    "RosbagSource",
    "SourceStats",
    "match_range_topics",
    "read_messages",
    "recording_name",
]

Kind = Literal["odometry", "range", "detection", "ground_truth"]

_DETECTION_TYPES = {"depthai": SPATIAL_DETECTION_ARRAY, "posearray": POSE_ARRAY}
_CLOCK_WINDOW_S = 5.0
"""How much of the bag's beginning the clock estimate looks at (receive time, s)."""
_CLOCK_SAMPLES = 200
"""At most this many header stamps per topic enter the clock estimate."""
_CLOCK_MISMATCH_S = 1.0
"""A topic whose clock differs from the others' by more than this gets a warning."""


class BagError(Exception):
    """The bag cannot be read as asked; the message says why in one line (or lists topics)."""


@dataclass
class SourceStats:
    """What one pass over a bag read, emitted and rejected."""

    messages: Counter[str] = field(default_factory=Counter)
    """Messages read per topic."""
    events: Counter[str] = field(default_factory=Counter)
    """Events emitted per kind: ``odometry``, ``range``, ``detection``, ``ground_truth``."""
    rejected: Counter[str] = field(default_factory=Counter)
    """Dropped values by reason (``range_nonfinite``, ``detection_zero_position``, ``late``...)."""
    restamped: Counter[str] = field(default_factory=Counter)
    """Messages per topic whose zero header stamp was replaced by receive time + offset."""
    repeated_ranges: int = 0
    """Ranges equal to the previous value of the same pair (passed through)."""
    clock_offset: float = 0.0
    """Estimated header stamp minus receive time (s), over all topics."""

    def as_dict(self) -> dict[str, Any]:
        """Plain-dict view for ``--json`` output."""
        return {
            "messages": dict(self.messages),
            "events": dict(self.events),
            "rejected": dict(self.rejected),
            "restamped": dict(self.restamped),
            "repeated_ranges": self.repeated_ranges,
            "clock_offset": self.clock_offset,
        }


@dataclass(frozen=True)
class _Route:
    """How the messages of one topic become events."""

    topic: str
    msgtype: str
    kind: Kind
    robot: str
    robot_b: str = ""
    node_a: str = ""
    node_b: str = ""
    camera: CameraConfig | None = None
    force_receive_time: bool = False


def recording_name(path: str | Path) -> str:
    """Name of the recording at ``path``: the bag folder's name (or the file's stem)."""
    p = Path(path)
    if p.is_file():
        return p.parent.name if (p.parent / "metadata.yaml").exists() else p.stem
    return p.name


@contextmanager
def _open_reader(path: Path) -> Iterator[Reader]:
    """Open a bag, turning every way it can fail into a :class:`BagError`."""
    if not path.exists():
        raise BagError(f"bag not found: {path}")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        raise BagError(
            f"not a rosbag2 bag: {path} has no metadata.yaml "
            "(give the bag folder, or its .db3/.mcap file)"
        )
    if path.is_file() and path.suffix not in (".db3", ".mcap"):
        raise BagError(
            f"not a rosbag2 bag: {path} (expected a bag folder with metadata.yaml, "
            "or a .db3/.mcap file)"
        )
    try:
        reader = Reader(path)
        reader.open()
    except BagError:
        raise
    except Exception as exc:  # rosbags/apsw/yaml raise many types for bad files
        raise BagError(f"cannot open bag {path}: {_reason(exc)}") from exc
    try:
        yield reader
    finally:
        # closing a half-broken database must not hide the real error
        with suppress(Exception):
            reader.close()


def _reason(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    lowered = text.lower()
    if any(w in lowered for w in ("malformed", "not a database", "corrupt", "disk image")):
        return f"the database is corrupted or truncated ({text})"
    return text


def _topic_regex(template: str) -> re.Pattern[str]:
    """Compile a range-topic template with ``{a}`` and ``{b}`` into a regex with named groups."""
    if "{a}" not in template or "{b}" not in template:
        raise BagError(f"uwb.range_topic {template!r} must contain both {{a}} and {{b}}")
    parts = re.split(r"(\{a\}|\{b\})", template)
    pattern = "".join(f"(?P<{p[1]}>[^/]+)" if p in ("{a}", "{b}") else re.escape(p) for p in parts)
    return re.compile(f"^{pattern}$")


def _guard(
    messages: Iterator[tuple[Any, int, bytes]], path: Path
) -> Iterator[tuple[Any, int, bytes]]:
    """Re-raise storage errors of a message iterator as :class:`BagError`."""
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except Exception as exc:  # apsw, sqlite, mcap, zstd: a damaged file
            raise BagError(f"cannot read bag {path}: {_reason(exc)}") from exc
        yield item


def match_range_topics(topics: Iterable[str], template: str) -> dict[str, tuple[str, str]]:
    """The topics matching a UWB range-topic template: topic -> (node a, node b)."""
    regex = _topic_regex(template)
    out: dict[str, tuple[str, str]] = {}
    for topic in sorted(topics):
        match = regex.match(topic)
        if match is not None:
            out[topic] = (match.group("a"), match.group("b"))
    return out


def read_messages(path: str | Path, topics: Collection[str]) -> Iterator[tuple[str, float, Any]]:
    """Decoded messages of some topics of a bag: ``(topic, receive time in s, message)``, in
    receive order, for analyses that need more than a team's events (e.g. every UWB node).

    Topics absent from the bag are a :class:`BagError`; undecodable messages are skipped.
    """
    path = Path(path)
    with _open_reader(path) as reader:
        present = {c.topic for c in reader.connections}
        missing = sorted(set(topics) - present)
        if missing:
            raise BagError(f"topic(s) {missing} not in the bag {path}; it has {sorted(present)}")
        conns = [c for c in reader.connections if c.topic in topics]
        messages = _guard(reader.messages(conns), path) if conns else iter(())
        for conn, recv_ns, raw in messages:
            try:
                msg = decode(raw, conn.msgtype)
            except MessageDecodeError:
                continue
            yield conn.topic, recv_ns * 1e-9, msg


class RosbagSource:
    """Iterable of the relloc events of one team in a rosbag2 recording, in header-time order.

    ``path`` is a bag folder (with ``metadata.yaml``) or a single ``.db3``/``.mcap`` file.
    Construction opens the bag, checks every configured topic and estimates the clock offset
    (raising :class:`BagError` on any problem); each iteration streams the bag anew and resets
    :attr:`stats`. ``ground_truth`` and ``detections`` switch those topics off (they are then
    not required to exist); ``objects`` names extra motion-capture bodies (e.g. ``"chair2"``)
    whose poses are emitted as ``GroundTruthEvent`` with the body name as ``robot``.
    ``max_lag`` bounds how late (s, header time behind the newest receive time) a message may
    arrive and still be put in order.
    """

    def __init__(
        self,
        path: str | Path,
        config: TeamConfig,
        *,
        ground_truth: bool = True,
        detections: bool = True,
        ranges: bool = True,
        odometry: bool = True,
        objects: tuple[str, ...] | list[str] = (),
        max_lag: float = 1.0,
    ) -> None:
        if max_lag <= 0:
            raise ValueError(f"max_lag must be positive, got {max_lag}")
        self.path = Path(path)
        self.config = config
        self.name = recording_name(self.path)
        self.max_lag = float(max_lag)
        self.warnings: list[str] = []
        """Non-fatal problems found when opening the bag (empty topics, odd clocks...)."""
        self.ignored_range_topics: list[str] = []
        """UWB topics of the bag involving a node that no robot of the team carries."""
        self.stats = SourceStats()
        self._zero_stamp_topics: set[str] = set()
        with _open_reader(self.path) as reader:
            self.bag_topics: dict[str, tuple[str, int]] = {
                name: (info.msgtype or "?", info.msgcount) for name, info in reader.topics.items()
            }
            """Every topic of the bag: name -> (message type, message count)."""
            self._routes = self._build_routes(
                ground_truth=ground_truth,
                detections=detections,
                ranges=ranges,
                odometry=odometry,
                objects=tuple(objects),
            )
            if reader.message_count:
                self._bag_start_ns, self._bag_end_ns = reader.start_time, reader.end_time
            else:
                self._bag_start_ns = self._bag_end_ns = 0
                self.warnings.append(f"the bag {self.path} has no messages")
            self._kind_offsets, offset = self._estimate_clock(reader)
        self.clock_offset: float = offset
        """Header stamp minus receive time (s), estimated over all read topics (or configured)."""
        self.stats.clock_offset = offset

    # ------------------------------------------------------------------ public properties
    @property
    def start_time(self) -> float:
        """First message of the bag, on the header clock (receive time + clock offset, s)."""
        return self._bag_start_ns * 1e-9 + self.clock_offset

    @property
    def end_time(self) -> float:
        """Last message of the bag, on the header clock (s)."""
        return self._bag_end_ns * 1e-9 + self.clock_offset

    @property
    def duration(self) -> float:
        """Length of the recording (s)."""
        return max(0.0, self.end_time - self.start_time)

    @property
    def topics(self) -> dict[str, str]:
        """The topics this source reads: topic -> kind of event."""
        return {topic: route.kind for topic, route in self._routes.items()}

    @property
    def zero_stamp_topics(self) -> set[str]:
        """Topics seen (at the start of the bag) with all-zero header stamps."""
        return set(self._zero_stamp_topics)

    def __repr__(self) -> str:
        return f"RosbagSource({str(self.path)!r}, team={self.config.name!r})"

    # ------------------------------------------------------------------ topic resolution
    def _missing(self, topic: str, what: str) -> BagError:
        listing = "\n".join(
            f"  {name}  [{msgtype}, {count} msgs]"
            for name, (msgtype, count) in sorted(self.bag_topics.items())
        )
        return BagError(
            f"topic {topic!r} ({what}) is not in the bag {self.path}; its topics are:\n{listing}"
        )

    def _require(self, topic: str, what: str, allowed: tuple[str, ...]) -> str:
        if topic not in self.bag_topics:
            raise self._missing(topic, what)
        msgtype, count = self.bag_topics[topic]
        if msgtype not in allowed:
            raise BagError(
                f"topic {topic!r} ({what}) has type {msgtype}, expected {' or '.join(allowed)}"
            )
        if count == 0:
            self.warnings.append(f"topic {topic} ({what}) has no messages")
        return msgtype

    def _build_routes(
        self,
        *,
        ground_truth: bool,
        detections: bool,
        ranges: bool,
        odometry: bool,
        objects: tuple[str, ...],
    ) -> dict[str, _Route]:
        cfg = self.config
        routes: dict[str, _Route] = {}
        for robot in cfg.robots:
            if odometry and robot.odom_topic:
                what = f"odometry of {robot.name}"
                msgtype = self._require(robot.odom_topic, what, (ODOMETRY,))
                routes[robot.odom_topic] = _Route(
                    robot.odom_topic,
                    msgtype,
                    "odometry",
                    robot.name,
                    force_receive_time=robot.odom_zero_stamps,
                )
            elif odometry:
                self.warnings.append(f"{robot.name} has no odom_topic: no odometry for it")
            if ground_truth and robot.mocap_body:
                topic = cfg.mocap_topic.format(body=robot.mocap_body)
                msgtype = self._require(topic, f"motion capture of {robot.name}", (POSE_STAMPED,))
                routes[topic] = _Route(topic, msgtype, "ground_truth", robot.name)
            if detections and robot.detection_topic:
                fmt = robot.detection_format
                allowed = (_DETECTION_TYPES[fmt],) if fmt else tuple(_DETECTION_TYPES.values())
                topic = robot.detection_topic
                msgtype = self._require(
                    topic, f"detections of {robot.name} ({fmt or 'any'})", allowed
                )
                routes[topic] = _Route(topic, msgtype, "detection", robot.name, camera=robot.camera)
        for body in objects:
            topic = cfg.mocap_topic.format(body=body)
            msgtype = self._require(topic, f"motion capture of object {body}", (POSE_STAMPED,))
            routes[topic] = _Route(topic, msgtype, "ground_truth", body)
        if ranges:
            routes.update(self._range_routes())
        return routes

    def _range_routes(self) -> dict[str, _Route]:
        cfg = self.config
        routes: dict[str, _Route] = {}
        for topic, (node_a, node_b) in match_range_topics(
            self.bag_topics, cfg.uwb.range_topic
        ).items():
            msgtype = self.bag_topics[topic][0]
            robot_a, robot_b = cfg.robot_of_node(node_a), cfg.robot_of_node(node_b)
            if robot_a is None or robot_b is None or robot_a == robot_b:
                self.ignored_range_topics.append(topic)
                continue
            if msgtype != RANGE:
                raise BagError(f"UWB topic {topic!r} has type {msgtype}, expected {RANGE}")
            routes[topic] = _Route(
                topic, msgtype, "range", robot_a, robot_b=robot_b, node_a=node_a, node_b=node_b
            )
        nodes = [r.uwb_node for r in cfg.robots if r.uwb_node]
        if len(nodes) >= 2 and not routes:
            self.warnings.append(
                f"no UWB range topic between the team's nodes {nodes} "
                f"(template {cfg.uwb.range_topic!r}): no ranges"
            )
        return routes

    # ------------------------------------------------------------------ clocks
    def _estimate_clock(self, reader: Reader) -> tuple[dict[str, float], float]:
        """Offsets ``header - receive`` (s) per event kind and overall, from the bag's start."""
        if self.config.clock_offset is not None:
            fixed = float(self.config.clock_offset)
            return {}, fixed
        conns = [c for c in reader.connections if c.topic in self._routes]
        per_topic: dict[str, list[float]] = defaultdict(list)
        zeros: Counter[str] = Counter()
        stop = reader.start_time + int(_CLOCK_WINDOW_S * 1e9)
        found = False
        # (an empty connection list would make rosbags read every topic)
        messages = _guard(reader.messages(conns), self.path) if conns else iter(())
        for conn, recv_ns, raw in messages:
            if recv_ns >= stop and found:
                break
            topic = conn.topic
            if len(per_topic[topic]) + zeros[topic] >= _CLOCK_SAMPLES:
                continue
            try:
                stamp = header_stamp_from_cdr(raw)
            except MessageDecodeError:
                continue
            if stamp == 0.0:
                zeros[topic] += 1
            else:
                per_topic[topic].append(stamp - recv_ns * 1e-9)
                found = True
        self._zero_stamp_topics = {t for t, n in zeros.items() if n and not per_topic.get(t)}
        medians = {t: statistics.median(v) for t, v in per_topic.items() if v}
        if not medians:
            if zeros:
                self.warnings.append("every header stamp is zero: using receive times")
            return {}, 0.0
        overall = statistics.median(medians.values())
        by_kind: dict[str, list[float]] = defaultdict(list)
        for topic, med in medians.items():
            by_kind[self._routes[topic].kind].append(med)
            if abs(med - overall) > _CLOCK_MISMATCH_S:
                self.warnings.append(
                    f"header clock of {topic} differs from the other topics by "
                    f"{med - overall:+.3f} s: events of different topics will not line up"
                )
        kind_offsets = {kind: statistics.median(v) for kind, v in by_kind.items()}
        return kind_offsets, overall

    def _offset(self, kind: str) -> float:
        return self._kind_offsets.get(kind, self.clock_offset)

    # ------------------------------------------------------------------ streaming
    def __iter__(self) -> Iterator[Event]:
        """Stream the bag's events in header-stamp order (resets :attr:`stats`)."""
        self.stats = stats = SourceStats(clock_offset=self.clock_offset)
        heap: list[tuple[float, int, Event]] = []
        seq = 0
        last_t = -math.inf
        last_range: dict[str, float] = {}

        def release(horizon: float) -> Iterator[Event]:
            """Events of the heap stamped up to ``horizon``, in order; later ones wait."""
            nonlocal last_t
            while heap and heap[0][0] <= horizon:
                t, _, ev = heapq.heappop(heap)
                if t < last_t:
                    stats.rejected["late"] += 1
                    continue
                last_t = t
                stats.events[_kind_of(ev)] += 1
                yield ev

        typestore()  # build the type store before the first message
        with _open_reader(self.path) as reader:
            conns = [c for c in reader.connections if c.topic in self._routes]
            messages = _guard(reader.messages(conns), self.path) if conns else iter(())
            for conn, recv_ns, raw in messages:
                route = self._routes[conn.topic]
                stats.messages[route.topic] += 1
                recv = recv_ns * 1e-9
                event = self._convert(route, raw, recv, stats, last_range)
                if event is not None:
                    heapq.heappush(heap, (event.t, seq, event))
                    seq += 1
                yield from release(recv + self.clock_offset - self.max_lag)
        yield from release(math.inf)

    def _convert(
        self,
        route: _Route,
        raw: bytes,
        recv: float,
        stats: SourceStats,
        last_range: dict[str, float],
    ) -> Event | None:
        try:
            msg = decode(raw, route.msgtype)
        except MessageDecodeError:
            stats.rejected["decode_error"] += 1
            return None
        t = stamp_to_sec(msg.header.stamp)
        if route.force_receive_time or t == 0.0:
            t = recv + self._offset(route.kind)
            stats.restamped[route.topic] += 1
        if route.kind == "odometry":
            return odometry_to_event(msg, route.robot, t=t)
        if route.kind == "ground_truth":
            event: GroundTruthEvent = pose_to_ground_truth(msg, route.robot, t=t)
            return event
        if route.kind == "range":
            value = float(msg.range)
            reason = range_rejection(value)
            if reason is not None:
                stats.rejected[f"range_{reason}"] += 1
                return None
            if last_range.get(route.topic) == value:
                stats.repeated_ranges += 1
            last_range[route.topic] = value
            return range_to_event(
                msg, route.robot, route.robot_b, node_a=route.node_a, node_b=route.node_b, t=t
            )
        assert route.camera is not None
        det, rejected = detections_to_event(msg, route.robot, route.camera, t=t)
        for reason, n in rejected.items():
            stats.rejected[f"detection_{reason}"] += n
        return det


_KIND_NAMES: dict[type, str] = {
    OdometryEvent: "odometry",
    RangeEvent: "range",
    DetectionEvent: "detection",
    GroundTruthEvent: "ground_truth",
}


def _kind_of(event: Event) -> str:
    return _KIND_NAMES.get(type(event), type(event).__name__)
