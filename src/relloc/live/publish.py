"""Publishing robots' messages into Zenoh: a recording (``relloc replay``) or simulated robots.

:func:`replay_bag` publishes a rosbag2 recording's raw CDR messages on the keys a bridge
(zenoh-bridge-ros2dds) would use, at the recorded pace times ``rate``, so a recording stands in
for live robots; :func:`publish_events` does the same for relloc events (the simulator's), as
:class:`EventEncoder` encodes them (the simulated robots of ``relloc sim-robots``,
:mod:`relloc.live.sim_robots`, use it too). Every message carries its send wall time as an attachment
(:func:`~relloc.sources.zenoh_source.encode_sent_time`): the server's trace turns it into
end-to-end latency.
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from relloc.config import RobotConfig, TeamConfig
from relloc.events import Event, GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.sources.zenoh_source import build_routes, encode_sent_time, key_for_topic

__all__ = [
    "SIM_TIME_BASE",
    "EventEncoder",
    "PublishStats",
    "Publishers",
    "ReplayOptions",
    "cmd_vel_key",
    "event_messages",
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

    def as_dict(self) -> dict[str, Any]:
        return {
            "messages": self.messages,
            "keys": len(self.per_key),
            "wall_s": round(self.wall_s, 3),
            "max_behind_s": round(self.max_behind_s, 4),
            "waited_s": round(self.waited_s, 3),
            "unmatched": self.unmatched,
        }


class Publishers:
    """Publishers declared on demand, each put carrying its send time as an attachment."""

    def __init__(self, session: Any) -> None:
        self.session = session
        self._pubs: dict[str, Any] = {}

    def get(self, key: str) -> Any:
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = self.session.declare_publisher(key)
        return pub

    def put(self, key: str, payload: bytes) -> None:
        self.get(key).put(payload, attachment=encode_sent_time(time.time()))

    def wait_matching(
        self, keys: Iterable[str], timeout: float, stop: Callable[[], bool]
    ) -> list[str]:
        """Wait until every key has a subscriber (or ``timeout``); returns those still without."""
        pending = list(dict.fromkeys(keys))
        end = time.time() + timeout
        while pending and time.time() < end and not stop():
            pending = [k for k in pending if not self.get(k).matching_status.matching]
            if pending:
                time.sleep(0.02)
        return pending

    def close(self) -> None:
        pubs, self._pubs = self._pubs, {}
        for pub in pubs.values():
            try:
                pub.undeclare()
            except Exception as exc:
                log.debug("undeclaring a publisher failed: %s", exc)


def _required_keys(config: TeamConfig, prefix: str, topic_keys: dict[str, str]) -> list[str]:
    """Keys, among those about to be published, that any server of ``config`` subscribes to
    (odometry and ranges; detections only with detection methods)."""
    kinds = {r.topic: r.kind for r in build_routes(config, prefix=prefix).values()}
    return sorted(k for t, k in topic_keys.items() if kinds.get(t) in ("odometry", "range"))


def _topic_keys(config: TeamConfig, prefix: str, topics: Iterable[str]) -> dict[str, str]:
    """The key each topic is published on: the team's topics on the first key a server
    subscribes them on (a range below its first robot's scope), others on ``prefix/<topic>``."""
    first: dict[str, str] = {}
    for key, route in build_routes(config, prefix=prefix).items():
        first.setdefault(route.topic, key)
    return {t: first.get(t) or key_for_topic(t, prefix=prefix) for t in topics}


def _run_schedule(
    items: Iterable[tuple[float, str, bytes]],
    pubs: Publishers,
    rate: float,
    stop: Callable[[], bool],
    stats: PublishStats,
    on_start: Callable[[], None] | None = None,
) -> None:
    """Publish ``(time s, key, payload)`` items (time ascending) at ``rate`` times their pace;
    ``on_start`` is called once, just before the first message goes out."""
    start_wall: float | None = None
    first_t = 0.0
    for t, key, payload in items:
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
        pubs.put(key, payload)
        stats.messages += 1
        stats.per_key[key] += 1
    if start_wall is not None:
        stats.wall_s = time.time() - start_wall


@dataclass(frozen=True)
class ReplayOptions:
    """How ``relloc replay`` publishes a recording."""

    rate: float = 1.0
    prefix: str = ""
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


def replay_bag(
    bag: Path,
    config: TeamConfig,
    session: Any,
    options: ReplayOptions | None = None,
    stop: Callable[[], bool] = lambda: False,
    on_start: Callable[[], None] | None = None,
) -> PublishStats:
    """Publish a bag's messages (raw CDR as stored) on the bridge-convention keys.

    Messages go out in receive order at the recorded pace divided by ``rate``; each carries its
    send wall time as an attachment. The team's topics are published on exactly the keys a
    :class:`~relloc.sources.zenoh_source.ZenohSource` of ``config`` subscribes to (with robot
    scopes and ``prefix``), every other topic on ``prefix/<topic>``; motion capture stays out
    unless ``ground_truth``.
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
    pubs = Publishers(session)
    try:
        routes = build_routes(config, prefix=opts.prefix)
        team_topics = {r.topic for r in routes.values()}
        mocap = re.compile(
            "^" + re.escape(config.mocap_topic).replace(re.escape("{body}"), "[^/]+") + "$"
        )
        conns = [
            c
            for c in reader.connections
            if c.msgcount
            and (not opts.team_only or c.topic in team_topics)
            and (opts.ground_truth or not mocap.match(c.topic))
        ]
        if not conns:
            raise BagError(f"nothing to replay in {bag} (team topics: {sorted(team_topics)})")
        if not 0.0 <= opts.start < (reader.end_time - reader.start_time) * 1e-9:
            raise BagError(
                f"--start {opts.start:g} s is outside {bag}, which lasts "
                f"{(reader.end_time - reader.start_time) * 1e-9:.1f} s"
            )
        keys = _topic_keys(config, opts.prefix, {c.topic for c in conns})
        required = _required_keys(config, opts.prefix, keys)
        t_wait = time.time()
        stats.unmatched = pubs.wait_matching(required, opts.wait, stop)
        stats.waited_s = time.time() - t_wait
        if stats.unmatched:
            log.warning("no subscriber yet for %s: publishing anyway", stats.unmatched)
        first_ns = reader.start_time + int(opts.start * 1e9)
        last_ns = math.inf if opts.duration is None else first_ns + opts.duration * 1e9

        def items() -> Iterator[tuple[float, str, bytes]]:
            for conn, recv_ns, raw in reader.messages(connections=conns):
                if recv_ns < first_ns:
                    continue
                if recv_ns > last_ns:
                    return
                yield recv_ns * 1e-9, keys[conn.topic], bytes(raw)

        _run_schedule(items(), pubs, opts.rate, stop, stats, on_start)
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


def cmd_vel_key(robot: RobotConfig, prefix: str = "") -> str:
    """The key of a robot's velocity commands: ``cmd_vel_topic`` (default ``/<robot>/cmd_vel``)
    under the bridge convention, e.g. ``tb1/cmd_vel``."""
    topic = robot.cmd_vel_topic or f"/{robot.name}/cmd_vel"
    return key_for_topic(topic, prefix=prefix, scope=robot.zenoh_scope)


class EventEncoder:
    """Relloc events as the ROS 2 messages a team would publish, on the keys it would use.

    Odometry becomes ``nav_msgs/Odometry`` on the robot's odometry key, a range
    ``sensor_msgs/Range`` on the key of its node pair (in the event's node order), and, with
    ``ground_truth``, a ground-truth pose ``geometry_msgs/PoseStamped`` on the robot's
    motion-capture key (``mocap_topic``); other events have no message. The keys are those a
    server of ``config`` subscribes to (:func:`~relloc.sources.zenoh_source.build_routes`).
    """

    def __init__(self, config: TeamConfig, *, prefix: str = "", ground_truth: bool = False) -> None:
        routes = build_routes(config, prefix=prefix, detections=False)
        self.odom_keys = {r.robot: k for k, r in routes.items() if r.kind == "odometry"}
        self.range_keys: dict[tuple[str, str], str] = {}
        for k, r in routes.items():
            if r.kind == "range":
                self.range_keys.setdefault((r.node_a, r.node_b), k)
        self.mocap_keys = {
            r.name: key_for_topic(config.mocap_topic.format(body=r.mocap_body or r.name), prefix=prefix)
            for r in config.robots
        }
        self.ground_truth = ground_truth

    def encode(self, ev: Event, time_base: float = 0.0) -> tuple[str, bytes] | None:
        """``(key, CDR payload)`` of one event, ``None`` if it has no message. ``time_base`` is
        added to the header stamp (the simulator starts at 0, and a zero stamp means "no stamp"
        on the wire)."""
        from relloc.ros.messages import encode, odometry_msg, pose_stamped_msg, range_msg

        if isinstance(ev, OdometryEvent):
            key = self.odom_keys.get(ev.robot)
            return None if key is None else (key, encode(odometry_msg(replace(ev, t=ev.t + time_base))))
        if isinstance(ev, RangeEvent):
            key = self.range_keys.get((ev.node_a, ev.node_b))
            return None if key is None else (key, encode(range_msg(replace(ev, t=ev.t + time_base))))
        if isinstance(ev, GroundTruthEvent) and self.ground_truth:
            return self.mocap_keys[ev.robot], encode(pose_stamped_msg(replace(ev, t=ev.t + time_base)))
        return None


def event_messages(
    events: Iterable[Event], config: TeamConfig, *, prefix: str = "", time_base: float = 0.0
) -> Iterator[tuple[float, str, bytes]]:
    """Relloc events as the messages :class:`EventEncoder` makes of them (no ground truth):
    ``(t, key, CDR payload)``, ``t`` the event's own time."""
    encoder = EventEncoder(config, prefix=prefix)
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
    prefix: str = "",
    time_base: float = 0.0,
    wait: float = 10.0,
    stop: Callable[[], bool] = lambda: False,
    on_start: Callable[[], None] | None = None,
) -> PublishStats:
    """Publish relloc events (e.g. from the simulator) on a team's keys in real time (times
    ``rate``), as :func:`event_messages` encodes them, after waiting up to ``wait`` s for
    subscribers of every key."""
    pubs = Publishers(session)
    stats = PublishStats()
    routes = build_routes(config, prefix=prefix, detections=False)
    keys = sorted(
        {k for k, r in routes.items() if r.kind == "odometry"}
        | {
            _first_range_key(routes, r.node_a, r.node_b)
            for r in routes.values()
            if r.kind == "range"
        }
    )
    try:
        t_wait = time.time()
        stats.unmatched = pubs.wait_matching(keys, wait, stop)
        stats.waited_s = time.time() - t_wait
        items = event_messages(events, config, prefix=prefix, time_base=time_base)
        _run_schedule(items, pubs, rate, stop, stats, on_start)
    finally:
        pubs.close()
    return stats


def _first_range_key(routes: dict[str, Any], node_a: str, node_b: str) -> str:
    return next(
        k
        for k, r in routes.items()
        if r.kind == "range" and (r.node_a, r.node_b) == (node_a, node_b)
    )
