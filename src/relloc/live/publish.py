"""Publishing robots' messages into Zenoh: a recording (``relloc replay``) or simulated robots.

:func:`replay_bag` publishes a rosbag2 recording's raw CDR messages as robots would, at the
recorded pace times ``rate``, so a recording stands in for live robots; :func:`publish_events`
does the same for relloc events (the simulator's), as :class:`EventEncoder` encodes them (the
simulated robots of ``relloc sim-robots``, :mod:`relloc.live.sim_robots`, use it too). The keys,
attachments and (with rmw_zenoh) liveliness tokens are those of the interface
(:class:`~relloc.ros.interfaces.RosInterface`), published by one
:class:`~relloc.ros.zenoh_node.ZenohNode`: on the bridge every message carries its send wall
time (:func:`~relloc.ros.interfaces.encode_sent_time`), with rmw_zenoh the rmw_zenoh attachment
whose source timestamp is that time; the server's trace turns either into end-to-end latency.
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections import Counter
from collections.abc import Callable, Hashable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from relloc.config import RobotConfig, TeamConfig
from relloc.events import Event
from relloc.faults import Faults
from relloc.live.message_faults import MessageFaults
from relloc.ros.interfaces import Channel, RosInterface
from relloc.ros.messages import (
    ODOMETRY,
    POSE_STAMPED,
    TWIST,
    MessageDecodeError,
    encode,
    in_distro,
)
from relloc.ros.zenoh_node import ZenohNode
from relloc.sensors import GROUND_TRUTH, ODOMETRY_SENSOR, RANGE_SENSOR, sensor, sensor_of
from relloc.sources.zenoh_keys import route_scopes

__all__ = [
    "SIM_TIME_BASE",
    "EventEncoder",
    "PublishStats",
    "Publishers",
    "ReplayOptions",
    "cmd_vel_channel",
    "event_messages",
    "odom_channel",
    "publish_events",
    "replay_bag",
    "simulated_team",
]

log = logging.getLogger(__name__)

SIM_TIME_BASE = 1_700_000_000.0
"""Added to the simulator's stamps when they go on the wire (a fixed value keeps runs
reproducible; zero stamps would mean "no stamp")."""


@dataclass
class PublishStats:
    """What a replay published."""

    messages: int = 0
    per_key: Counter[str] = field(default_factory=Counter)
    wall_s: float = 0.0
    max_behind_s: float = 0.0
    """Worst delay of a send behind its schedule (the publisher could not keep up)."""
    waited_s: float = 0.0
    """Time spent waiting for the server's subscribers before the first message."""
    unmatched: list[str] = field(default_factory=list)
    """Required keys that still had no subscriber when publishing started."""
    injected: dict[str, int] = field(default_factory=dict)
    """What the injected faults did (``dropped``, ``silenced``, ``changed``, ``shifted``)."""

    def as_dict(self) -> dict[str, Any]:
        return {
            "messages": self.messages,
            "keys": len(self.per_key),
            "wall_s": round(self.wall_s, 3),
            "max_behind_s": round(self.max_behind_s, 4),
            "waited_s": round(self.waited_s, 3),
            "unmatched": self.unmatched,
            "injected_faults": dict(self.injected),
        }


class Publishers:
    """The publishers of one process standing in for robots: a :class:`ZenohNode` (declaring
    each channel's publisher on first use, attaching send times or rmw_zenoh attachments)."""

    def __init__(
        self, session: Any, interface: RosInterface | None = None, node: str = "relloc_replay"
    ) -> None:
        self.session = session
        self.node = ZenohNode(session, interface or RosInterface(), node)

    def put(self, channel: Channel, payload: bytes) -> None:
        self.node.put(channel, payload)

    def wait_matching(
        self, channels: Iterable[Channel], timeout: float, stop: Callable[[], bool]
    ) -> list[str]:
        """Wait until every channel has a subscriber (or ``timeout``); returns the keys of those
        still without."""
        return self.node.wait_matching(list(channels), timeout, stop)

    def close(self) -> None:
        self.node.close()


def _first_scopes(config: TeamConfig) -> dict[str, str]:
    """Each team topic's first namespace (a range below its first robot's scope)."""
    first: dict[str, str] = {}
    for route, scope in route_scopes(config):
        first.setdefault(route.topic, scope)
    return first


def _topic_channels(
    config: TeamConfig, interface: RosInterface, prefix: str, topics: dict[str, str]
) -> dict[str, Channel]:
    """The channel each topic (name -> message type) is published on: the team's topics on the
    first key a server subscribes them on, others below ``prefix`` alone."""
    first = _first_scopes(config)
    channels: dict[str, Channel] = {}
    for t, msgtype in topics.items():
        try:
            channels[t] = interface.channel(t, msgtype, prefix=prefix, scope=first.get(t, ""))
        except MessageDecodeError as exc:  # rmw_zenoh needs the type's hash: its definition
            log.warning("%s is not replayed: %s", t, exc)
    return channels


def _required(config: TeamConfig, channels: dict[str, Channel]) -> list[Channel]:
    """Channels, among those about to be published, that any server of ``config`` subscribes
    to (the topics of ``essential`` sensors: odometry and ranges; detections only with
    detection methods)."""
    kinds = {r.topic: r.kind for r, _ in route_scopes(config)}
    return [c for t, c in sorted(channels.items()) if t in kinds and sensor(kinds[t]).essential]


def _run_schedule(
    items: Iterable[tuple[float, Channel, bytes]],
    pubs: Publishers,
    rate: float,
    stop: Callable[[], bool],
    stats: PublishStats,
    on_start: Callable[[], None] | None = None,
) -> None:
    """Publish ``(time s, channel, payload)`` items (time ascending) at ``rate`` times their pace;
    ``on_start`` is called once, just before the first message goes out."""
    start_wall: float | None = None
    first_t = 0.0
    for t, channel, payload in items:
        if stop():
            break
        if start_wall is None:
            if on_start is not None:
                on_start()
            start_wall, first_t = time.time(), t
        due = start_wall + (t - first_t) / rate
        delay = due - time.time()
        if delay > 0:
            time.sleep(delay)
        else:
            stats.max_behind_s = max(stats.max_behind_s, -delay)
        pubs.put(channel, payload)
        stats.messages += 1
        stats.per_key[channel.topic_key] += 1
    if start_wall is not None:
        stats.wall_s = time.time() - start_wall


@dataclass(frozen=True)
class ReplayOptions:
    """How ``relloc replay`` publishes a recording."""

    rate: float = 1.0
    prefix: str = ""
    interface: RosInterface = field(default_factory=RosInterface)
    """Publish as robots behind a bridge (``bridge``) or running ``rmw_zenoh``."""
    team_only: bool = False
    """Publish only the team's topics (odometry, UWB between its robots, detections)."""
    ground_truth: bool = False
    """Also publish motion capture (topics matching the config's ``mocap_topic``): robots do
    not have it live, and evaluation reads it from the bag itself."""
    wait: float = 10.0
    """Seconds to wait for subscribers of the team's odometry and range keys before starting."""
    start: float = 0.0
    """Skip this many seconds at the start of the bag."""
    duration: float | None = None
    faults: Faults = field(default_factory=Faults)
    """Faults injected into the team's messages before they go out
    (:mod:`relloc.live.message_faults`)."""


def replay_bag(
    bag: Path,
    config: TeamConfig,
    session: Any,
    options: ReplayOptions | None = None,
    stop: Callable[[], bool] = lambda: False,
    on_start: Callable[[], None] | None = None,
) -> PublishStats:
    """Publish a bag's messages (raw CDR as stored) as the robots would, on the interface's keys
    (a type whose layout differs in the interface's distribution is written in that layout).

    Messages go out in receive order at the recorded pace divided by ``rate``; each carries the
    interface's attachment (the send wall time). The team's topics are published on exactly the
    keys a :class:`~relloc.sources.zenoh_source.ZenohSource` of ``config`` subscribes to (with
    robot scopes and ``prefix``), every other topic below ``prefix`` alone; motion capture stays
    out unless ``ground_truth``. With ``faults``, the team's messages are faulted on the way
    (decoded, changed, encoded again: :class:`~relloc.live.message_faults.MessageFaults`).
    """
    from rosbags.rosbag2 import Reader

    from relloc.sources.rosbag import BagError

    opts = options or ReplayOptions()
    if not opts.rate > 0:
        raise ValueError(f"--rate must be positive, got {opts.rate}")
    bag = Path(bag)
    if not bag.exists():
        raise BagError(f"bag not found: {bag}")
    try:
        reader = Reader(bag)
        reader.open()
    except Exception as exc:
        raise BagError(f"cannot open bag {bag}: {exc}") from exc
    stats = PublishStats()
    pubs = Publishers(session, opts.interface, "relloc_replay")
    try:
        team_topics = {r.topic for r, _ in route_scopes(config)}
        mocap = re.compile(
            "^" + re.escape(config.mocap_topic).replace(re.escape("{body}"), "[^/]+") + "$"
        )
        faulted = MessageFaults(config, opts.faults) if opts.faults.active else None
        published = [
            c
            for c in reader.connections
            if c.msgcount
            and (not opts.team_only or c.topic in team_topics)
            and (opts.ground_truth or not mocap.match(c.topic))
        ]
        if not published:
            raise BagError(f"nothing to replay in {bag} (team topics: {sorted(team_topics)})")
        # A kidnapping moves ranges by the robots' true positions: the faults read motion
        # capture even where it is not published.
        read = {c.topic for c in published} | (
            faulted.topics() if faulted and opts.faults.kidnap else set()
        )
        conns = [c for c in reader.connections if c.msgcount and c.topic in read]
        if not 0.0 <= opts.start < (reader.end_time - reader.start_time) * 1e-9:
            raise BagError(
                f"--start {opts.start:g} s is outside {bag}, which lasts "
                f"{(reader.end_time - reader.start_time) * 1e-9:.1f} s"
            )
        channels = _topic_channels(
            config, opts.interface, opts.prefix, {c.topic: c.msgtype for c in published}
        )
        t_wait = time.time()
        stats.unmatched = pubs.wait_matching(_required(config, channels), opts.wait, stop)
        stats.waited_s = time.time() - t_wait
        if stats.unmatched:
            log.warning("no subscriber yet for %s: publishing anyway", stats.unmatched)
        first_ns = reader.start_time + int(opts.start * 1e9)
        last_ns = math.inf if opts.duration is None else first_ns + opts.duration * 1e9

        def items() -> Iterator[tuple[float, Channel, bytes]]:
            for conn, recv_ns, raw in reader.messages(connections=conns):
                if recv_ns < first_ns:
                    continue
                if recv_ns > last_ns:
                    return
                data = bytes(raw)
                payload: bytes | None = data
                if faulted is not None:
                    try:
                        payload = faulted(conn.topic, conn.msgtype, data, recv_ns * 1e-9)
                    except MessageDecodeError as exc:  # a damaged message goes out as it is
                        log.warning("%s: not faulted (%s)", conn.topic, exc)
                if payload is not None and conn.topic in channels:
                    channel = channels[conn.topic]
                    yield (
                        recv_ns * 1e-9,
                        channel,
                        in_distro(payload, channel.msgtype, channel.distro),
                    )

        _run_schedule(items(), pubs, opts.rate, stop, stats, on_start)
        if faulted is not None:
            stats.injected = dict(faulted.counts)
    finally:
        pubs.close()
        reader.close()
    return stats


def simulated_team(seed: int = 0, duration: float = 30.0) -> tuple[Any, TeamConfig]:
    """The paper's five-robot simulated team, with ROS topics so it can go over Zenoh.

    Returns ``(Simulation, config)``: the config is the simulator's own (truthful calibration)
    with odometry on ``/<robot>/odom`` and UWB on the default ``/uwb/tof/{a}/{b}/distance``.
    """
    from relloc.simulator import multi_scenario

    sim = multi_scenario(seed, duration=duration)
    config = sim.config
    for robot in config.robot_names:
        config = config.with_robot(robot, odom_topic=f"/{robot}/odom")
    return sim, config


def cmd_vel_channel(
    robot: RobotConfig, interface: RosInterface | None = None, prefix: str = ""
) -> Channel:
    """The channel of a robot's velocity commands: ``geometry_msgs/Twist`` on ``cmd_vel_topic``
    (default ``/<robot>/cmd_vel``) below its scope, e.g. the key ``r2/cmd_vel`` on the bridge."""
    topic = robot.cmd_vel_topic or f"/{robot.name}/cmd_vel"
    return (interface or RosInterface()).channel(
        topic, TWIST, prefix=prefix, scope=robot.zenoh_scope
    )


def odom_channel(
    robot: RobotConfig, interface: RosInterface | None = None, prefix: str = ""
) -> Channel:
    """The channel of a robot's odometry (``odom_topic``, default ``/<robot>/odom``)."""
    topic = robot.odom_topic or f"/{robot.name}/odom"
    return (interface or RosInterface()).channel(
        topic, ODOMETRY, prefix=prefix, scope=robot.zenoh_scope
    )


class EventEncoder:
    """Relloc events as the ROS 2 messages a team would publish, on the channels it would use.

    Each event goes out as its sensor's :meth:`~relloc.sensors.Sensor.message` on the topic
    its sensor's :meth:`~relloc.sensors.Sensor.event_key` picks among that sensor's routes:
    odometry as ``nav_msgs/Odometry`` on the robot's odometry topic, a range as
    ``sensor_msgs/Range`` on the topic of its node pair (in the event's node order), a plug-in's
    events as its own messages, and, with ``ground_truth``, a ground-truth pose
    ``geometry_msgs/PoseStamped`` on the robot's motion-capture topic (``mocap_topic``); other
    events have no message. The keys are those a server of ``config`` on the same interface
    subscribes to (:func:`~relloc.sources.zenoh_keys.build_routes`; detections left out).
    """

    def __init__(
        self,
        config: TeamConfig,
        *,
        interface: RosInterface | None = None,
        prefix: str = "",
        ground_truth: bool = False,
    ) -> None:
        iface = interface or RosInterface()
        self._channels: dict[str, dict[Hashable, Channel]] = {}
        """Per sensor kind, its channels by :meth:`~relloc.sensors.Sensor.channel_key`."""
        for route, scope in route_scopes(config, detections=False):
            own = sensor(route.kind)
            if not own.writes(route):
                continue
            self._channels.setdefault(route.kind, {}).setdefault(
                own.channel_key(route),
                iface.channel(route.topic, route.msgtypes[0], prefix=prefix, scope=scope),
            )
        self._channels[GROUND_TRUTH.kind] = {
            r.name: iface.channel(
                config.mocap_topic.format(body=r.mocap_body or r.name), POSE_STAMPED, prefix=prefix
            )
            for r in config.robots
        }
        self.distro = iface.distro
        self.odom_keys = {r: c.key for r, c in self._channels.get(ODOMETRY_SENSOR.kind, {}).items()}
        self.range_keys = {p: c.key for p, c in self._channels.get(RANGE_SENSOR.kind, {}).items()}
        self.ground_truth = ground_truth

    @property
    def channels(self) -> list[Channel]:
        """The channels of the ``essential`` sensors (odometry, ranges: what a server subscribes to)."""
        return [
            c
            for kind, of_kind in self._channels.items()
            if sensor(kind).essential
            for c in of_kind.values()
        ]

    def encode(self, ev: Event, time_base: float = 0.0) -> tuple[Channel, bytes] | None:
        """``(channel, CDR payload)`` of one event, ``None`` if it has no message. ``time_base``
        is added to the header stamp (the simulator starts at 0, and a zero stamp means "no
        stamp" on the wire)."""
        own = sensor_of(ev)
        if own is None or (own is GROUND_TRUTH and not self.ground_truth):
            return None
        ch = self._channels.get(own.kind, {}).get(own.event_key(ev))
        if ch is None:
            return None
        msg = own.message(replace(ev, t=ev.t + time_base))
        return None if msg is None else (ch, encode(msg, distro=self.distro))


def event_messages(
    events: Iterable[Event],
    config: TeamConfig,
    *,
    interface: RosInterface | None = None,
    prefix: str = "",
    time_base: float = 0.0,
) -> Iterator[tuple[float, Channel, bytes]]:
    """Relloc events as the messages :class:`EventEncoder` makes of them (no ground truth):
    ``(t, channel, CDR payload)``, ``t`` the event's own time."""
    encoder = EventEncoder(config, interface=interface, prefix=prefix)
    for ev in events:
        out = encoder.encode(ev, time_base)
        if out is not None:
            yield ev.t, *out


def publish_events(
    events: Iterable[Event],
    config: TeamConfig,
    session: Any,
    *,
    rate: float = 1.0,
    interface: RosInterface | None = None,
    prefix: str = "",
    time_base: float = 0.0,
    wait: float = 10.0,
    stop: Callable[[], bool] = lambda: False,
    on_start: Callable[[], None] | None = None,
) -> PublishStats:
    """Publish relloc events (e.g. from the simulator) on a team's channels in real time (times
    ``rate``), as :func:`event_messages` encodes them, after waiting up to ``wait`` s for
    subscribers of every odometry and range channel."""
    pubs = Publishers(session, interface, "relloc_events")
    stats = PublishStats()
    encoder = EventEncoder(config, interface=interface, prefix=prefix)
    try:
        t_wait = time.time()
        stats.unmatched = pubs.wait_matching(encoder.channels, wait, stop)
        stats.waited_s = time.time() - t_wait
        items = event_messages(
            events, config, interface=interface, prefix=prefix, time_base=time_base
        )
        _run_schedule(items, pubs, rate, stop, stats, on_start)
    finally:
        pubs.close()
    return stats
