"""rosbag2 recordings (sqlite3 or MCAP) as a time-ordered stream of relloc events.

:class:`RosbagSource` reads a bag with ``rosbags`` (no ROS installation needed) and yields the
events of one team, described by its :class:`~relloc.config.TeamConfig`. This module is only
the transport: opening and checking the bag, and reading its messages in receive order. What
the messages become (routes, conversion, clock, reorder buffer, counters) is the shared
ingestion layer, :mod:`relloc.sources.ingest`, which the live Zenoh source uses too.

The derivation: docs/explanation/internals.md, section ``relloc.sources.rosbag``.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Callable, Collection, Iterator, Mapping
from contextlib import contextmanager, suppress
from dataclasses import replace
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import Reader
from rosbags.typesys import get_types_from_msg

from relloc.config import ConfigError, TeamConfig
from relloc.events import Event, GroundTruthEvent
from relloc.ros.distros import Layout, layout_of_definition, layouts
from relloc.ros.messages import MessageDecodeError, decode, header_stamp_from_cdr, typestore
from relloc.ros.stores import register_types
from relloc.sensors import Route, Sensor, sensor
from relloc.sources.clock import HeaderClock
from relloc.sources.ingest import (
    Converter,
    IngestStats,
    match_range_topics,
    switched_on,
    team_routes,
)
from relloc.sources.reorder import ReorderBuffer
from relloc.sources.salvage import readable_rows, salvaged_copy

__all__ = ["BagError", "RosbagSource", "read_messages", "recording_name"]

log = logging.getLogger(__name__)

_CLOCK_WINDOW_S = 5.0
"""How much of the bag's beginning the clock estimate looks at (receive time, s)."""
_CLOCK_SAMPLES = 200
"""At most this many header stamps per topic enter the clock estimate."""
_CLOCK_MISMATCH_S = 1.0
"""A topic whose clock differs from the others' by more than this gets a warning."""


class BagError(Exception):
    """The bag cannot be read as asked; the message says why in one line (or lists topics)."""


def recording_name(path: str | Path) -> str:
    """Name of the recording at ``path``: the bag folder's name (or the file's stem)."""
    p = Path(path)
    if p.is_file():
        return p.parent.name if (p.parent / "metadata.yaml").exists() else p.stem
    return p.name


@contextmanager
def _open_reader(path: Path, on_damage: Callable[[str], None] | None = None) -> Iterator[Reader]:
    """Open a bag, turning every way it can fail into a :class:`BagError`. With ``on_damage``,
    a ``.db3`` bag whose database cannot be opened is salvaged instead (:func:`~relloc.sources.salvage.salvaged_copy`):
    the reader reads what is readable, and ``on_damage`` gets a line saying how much was lost."""
    folder: Path | None = None
    try:
        reader = _opened(path)
    except BagError as exc:
        salvage = (
            salvaged_copy(path)
            if on_damage is not None and "corrupted or truncated" in str(exc)
            else None
        )
        if salvage is None:
            raise
        folder, line = salvage
        assert on_damage is not None
        on_damage(f"bag {path} is damaged: {line}; reading what is readable")
        reader = _opened(folder)
    try:
        yield reader
    finally:
        # closing a half-broken database must not hide the real error
        with suppress(Exception):
            reader.close()
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)


def _opened(path: Path) -> Reader:
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
        if path.is_dir() and _metadata_problem(exc):
            raise BagError(
                f"cannot open bag {path}: its metadata.yaml is not rosbag2 metadata (a YAML file with a "
                f"rosbag2_bagfile_information table, as ros2 bag record writes it): {' '.join(_reason(exc).split())}"
            ) from exc
        raise BagError(f"cannot open bag {path}: {_reason(exc)}") from exc
    return reader


def _metadata_problem(exc: BaseException) -> bool:
    """Whether opening failed on the bag's ``metadata.yaml`` (undecodable, not YAML, or without
    the keys rosbag2 writes) rather than on its storage."""
    text = str(exc).lower()
    if "database" in text:
        return False
    name = type(exc).__name__.lower()
    return (
        isinstance(exc, UnicodeDecodeError | KeyError)
        or "metadata" in text
        or "yaml" in name
        or "scanner" in name
        or "parser" in name
    )


def _reason(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    lowered = text.lower()
    if any(w in lowered for w in ("malformed", "not a database", "corrupt", "disk image")):
        return f"the database is corrupted or truncated ({text})"
    return text


def _messages(
    reader: Reader,
    path: Path,
    topics: Collection[str],
    on_damage: Callable[[str], None] | None = None,
) -> Iterator[tuple[Any, int, bytes]]:
    """``(connection, receive time in ns, raw CDR)`` of some topics in receive order. A
    storage error is a :class:`BagError`, or, with ``on_damage``, the end of what is readable:
    ``on_damage`` gets a line saying how many of the messages the metadata lists were read."""
    conns = [c for c in reader.connections if c.topic in topics]
    if not conns:  # an empty connection list would make rosbags read every topic
        return
    messages = reader.messages(conns)
    read = 0
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except Exception as exc:  # apsw, sqlite, mcap, zstd: a damaged file
            if on_damage is None:
                raise BagError(f"cannot read bag {path}: {_reason(exc)}") from exc
            rest = readable_rows(path, conns, after=read)
            listed = sum(c.msgcount for c in conns)
            lost = max(listed - read - len(rest), 0)
            on_damage(
                f"bag {path} is damaged: read {read + len(rest)} of the {listed} messages of the team's "
                f"topics, {lost} ({100.0 * lost / max(listed, 1):.0f} %) lost ({_reason(exc)})"
            )
            yield from rest
            return
        read += 1
        yield item


def _bag_layouts(reader: Reader) -> dict[str, Layout]:
    """Per topic, the layout its stored definition names. A type relloc does not know is
    registered from the bag's definition (a driver's own message, recorded with it)."""
    found: dict[str, Layout] = {}
    for conn in reader.connections:
        text = conn.msgdef.data if conn.msgdef is not None else ""
        if not text or conn.msgdef.format.name != "MSG":
            continue
        if not layouts(conn.msgtype):
            with suppress(Exception):  # an unparsable definition: the type stays unknown
                register_types(get_types_from_msg(text, conn.msgtype))
        layout = layout_of_definition(conn.msgtype, text)
        if layout is not None:
            found[conn.topic] = layout
    return found


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
        for conn, recv_ns, raw in _messages(reader, path, topics):
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
    :attr:`stats`. ``ground_truth``, ``detections``, ``ranges`` and ``odometry`` switch those
    topics off (they are then not required to exist); ``objects`` names extra motion-capture
    bodies (e.g. ``"chair2"``) whose poses are emitted as ``GroundTruthEvent`` with the body
    name as ``robot`` (with their height, ``(x, y, z)``, for a team of ``dimension`` 3; planar
    for a ground team). ``max_lag`` bounds how late (s, header time behind the newest receive
    time) a message may arrive and still be put in order.
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
        """UWB topics of the bag involving a node that no robot of the team carries (what the
        sensors' :meth:`~relloc.sensors.Sensor.bag_check` leave unread)."""
        with _open_reader(self.path, self._damaged) as reader:
            self.bag_topics: dict[str, tuple[str, int]] = {
                name: (info.msgtype or "?", info.msgcount) for name, info in reader.topics.items()
            }
            """Every topic of the bag: name -> (message type, message count)."""
            self.layouts = _bag_layouts(reader)
            """Per topic, the layout of its type the bag's own definition names (bags that store
            definitions: MCAP, rosbag2 since Iron); other topics' messages are tried in each."""
            try:
                routes = team_routes(
                    config,
                    odometry=odometry,
                    ranges=ranges,
                    detections=detections,
                    ground_truth=ground_truth,
                    objects=tuple(objects),
                )
            except ConfigError as exc:
                raise BagError(str(exc)) from None
            on = switched_on(
                odometry=odometry, ranges=ranges, detections=detections, ground_truth=ground_truth
            )
            self._routes = self._resolve(routes, on)
            if reader.message_count:
                self._bag_start_ns, self._bag_end_ns = reader.start_time, reader.end_time
            else:
                self._bag_start_ns = self._bag_end_ns = 0
                self.warnings.append(f"the bag {self.path} has no messages")
            self.clock = self._scan_clock(reader)
            """The header clock, estimated from the bag's first seconds and frozen."""
        self.clock_offset: float = self.clock.overall
        """Header stamp minus receive time (s), estimated over all read topics (or configured)."""
        self.stats = IngestStats(clock_offset=self.clock_offset)

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
        return self.clock.zero_stamp_streams

    def __repr__(self) -> str:
        return f"RosbagSource({str(self.path)!r}, team={self.config.name!r})"

    def initial_poses(self) -> None:
        """A bag says nothing of the true start beyond its motion capture: ``None``."""
        return None

    def check_ranges(self) -> None:
        """What a run over this bag needs of its UWB topics: robots none of whose tags matches
        a range topic get a warning (only their odometry moves them from the uniform prior);
        no range at all between the team's robots is a :class:`BagError`, since every method
        fuses ranges."""
        template = self.config.uwb.range_topic
        if self.config.uwb.peer_field:  # one topic per node, listing any of its peers
            every = tuple(n for r in self.config.robots for n in r.nodes)
            found: Mapping[str, tuple[str, ...]] = {
                t: every for t, r in self._routes.items() if r.kind == "range"
            }
        else:
            found = match_range_topics(self.topics, template)
        ranged = {node for pair in found.values() for node in pair}
        robots = [r for r in self.config.robots if r.nodes]
        if len(robots) >= 2 and not found:
            nodes = ", ".join(f"{r.name}={'/'.join(r.nodes)}" for r in robots)
            raise BagError(
                f"no UWB range topic of the bag joins two of the team's nodes ({nodes}; template "
                f"{template!r}): every method needs ranges; check uwb_node and uwb.range_topic"
            )
        self.warnings += [
            f"{r.name}: uwb_node {'/'.join(r.nodes)!r} matches no range topic of the bag (template "
            f"{template!r}): it gets no range, so only its odometry moves it from the uniform prior"
            for r in robots
            if found and not ranged.intersection(r.nodes)
        ]

    # ------------------------------------------------------------------ topics against the bag
    def _resolve(self, routes: list[Route], sensors: list[Sensor]) -> dict[str, Route]:
        """The routes whose topics the bag has, each with the bag's message type; what the
        switched-on ``sensors`` say about the config and the bag goes to the warnings."""
        for s in sensors:
            self.warnings += s.config_warnings(self.config)
        resolved: dict[str, Route] = {}
        of_kind: dict[str, list[Route]] = {s.kind: [] for s in sensors}
        for route in routes:
            own = sensor(route.kind)
            if not own.required and route.topic not in self.bag_topics:
                continue  # a pair without a topic simply has no ranges (sightings)
            if route.topic not in self.bag_topics:
                raise self._missing(route)
            msgtype, count = self.bag_topics[route.topic]
            if msgtype not in route.msgtypes:
                raise BagError(
                    f"topic {route.topic!r} ({route.what}) has type {msgtype}, "
                    f"expected {' or '.join(route.msgtypes)}"
                )
            if count == 0 and own.warn_empty:
                self.warnings.append(f"topic {route.topic} ({route.what}) has no messages")
            resolved[route.topic] = replace(route, msgtypes=(msgtype,))
            of_kind.setdefault(route.kind, []).append(resolved[route.topic])
        for s in sensors:
            ignored, warnings = s.bag_check(self.config, self.bag_topics, of_kind[s.kind])
            self.ignored_range_topics += ignored
            self.warnings += warnings
        return resolved

    def _missing(self, route: Route) -> BagError:
        listing = "\n".join(
            f"  {name}  [{msgtype}, {count} msgs]"
            for name, (msgtype, count) in sorted(self.bag_topics.items())
        )
        return BagError(
            f"topic {route.topic!r} ({route.what}) is not in the bag {self.path}; "
            f"its topics are:\n{listing}"
        )

    # ------------------------------------------------------------------ clock
    def _damaged(self, line: str) -> None:
        """A damaged bag read as far as readable: warned once (and logged)."""
        if line not in self.warnings:
            log.warning("%s", line)
            self.warnings.append(line)

    def _scan_clock(self, reader: Reader) -> HeaderClock:
        """The header clock learnt from the first header stamps of every read topic, frozen."""
        clock = HeaderClock(fixed_offset=self.config.clock_offset)
        if clock.fixed_offset is None:
            stop = reader.start_time + int(_CLOCK_WINDOW_S * 1e9)
            found = False
            for conn, recv_ns, raw in _messages(reader, self.path, self._routes):
                if recv_ns >= stop and found:
                    break
                topic = conn.topic
                if clock.seen(topic) >= _CLOCK_SAMPLES or not self._routes[topic].stamped:
                    continue
                try:
                    stamp = header_stamp_from_cdr(raw)
                except MessageDecodeError:
                    continue
                clock.observe(topic, self._routes[topic].kind, stamp, recv_ns * 1e-9)
                found = found or stamp != 0.0
            offsets = clock.stream_offsets()
            if not offsets and clock.zeros_seen:
                self.warnings.append("every header stamp is zero: using receive times")
            overall = clock.overall
            for topic, offset in offsets.items():
                if abs(offset - overall) > _CLOCK_MISMATCH_S:
                    self.warnings.append(
                        f"header clock of {topic} differs from the other topics by "
                        f"{offset - overall:+.3f} s: events of different topics will not line up"
                    )
        clock.freeze()
        return clock

    # ------------------------------------------------------------------ streaming
    def __iter__(self) -> Iterator[Event]:
        """Stream the bag's events in header-stamp order (resets :attr:`stats`)."""
        self.stats = stats = IngestStats(clock_offset=self.clock_offset)
        converter = Converter(stats, self.clock, distro=self.config.ros_distro)
        layouts = self.layouts
        buffer: ReorderBuffer[Event] = ReorderBuffer(self.max_lag, drop_late=True)

        def released(events: list[Event]) -> list[Event]:
            for event in events:
                stats.emitted(event)
            if buffer.late:
                stats.rejected["late"] = buffer.late
            return events

        typestore(self.config.ros_distro)  # build the type store before the first message

        def damaged(line: str) -> None:
            self._damaged(line)
            stats.rejected["bag_damaged"] += 1

        heights = self.config.dimension == 3
        with _open_reader(self.path, damaged) as reader:
            for conn, recv_ns, raw in _messages(reader, self.path, self._routes, damaged):
                recv = recv_ns * 1e-9
                layout = layouts.get(conn.topic)
                for event in converter.events(
                    self._routes[conn.topic], conn.topic, raw, recv, layout
                ):
                    if heights and isinstance(event, GroundTruthEvent):
                        event = _with_height(event, raw, conn.msgtype, layout)
                    buffer.push(event.t, event)
                buffer.advance(recv + self.clock_offset)
                yield from released(buffer.pop_ready())
        yield from released(buffer.flush())


def _with_height(
    event: GroundTruthEvent, raw: bytes, msgtype: str, layout: Layout | None
) -> GroundTruthEvent:
    """``event`` (motion capture, planar as converted) with its message's height: the full
    pose ``(x, y, z)`` and yaw a flying team is scored against (a ground team's stays planar).
    A message that does not decode keeps the planar pose."""
    try:
        msg = decode(raw, msgtype, layout)
    except MessageDecodeError:
        return event
    if hasattr(msg, "transform"):  # TransformStamped; the other MOCAP_TYPES nest a pose
        position = msg.transform.translation
    else:
        position = (msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose).position
    return replace(event, position=(event.position[0], event.position[1], float(position.z)))
