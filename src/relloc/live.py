"""The live engine over Eclipse Zenoh: ``relloc serve``, ``relloc replay``, ``relloc bench resources``.

``serve`` runs the *same* :class:`~relloc.engine.Engine` and method pipelines as ``relloc run``
and the demo, fed by :class:`~relloc.sources.zenoh_source.ZenohSource` (the robots' ROS 2
topics as bridged by zenoh-bridge-ros2dds) and publishing through
:class:`~relloc.sinks.zenoh_sink.ZenohSink`. One thread runs the engine; Zenoh's callbacks only
enqueue. ``replay`` publishes a rosbag2 recording's raw CDR messages on the bridge's keys at
the recorded pace (times ``--rate``), so a recording stands in for the robots;
``bench resources`` runs both on loopback and measures the server process (CPU, peak RSS,
end-to-end latency). ``docs/live.md`` tells the whole story and gives the measured figures.

Latency is traced, not guessed: the replay attaches its send wall time to every message
(:func:`~relloc.sources.zenoh_source.encode_sent_time`); the server, run with ``--trace``,
publishes for each estimate the message whose arrival produced it (its key, header stamp and
send/receive times) and the estimate's publication time on ``relloc/trace``. Both ends share the
host's wall clock on loopback.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
import signal
import socket
import statistics
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from relloc.config import TeamConfig
from relloc.engine import Engine, Pipeline
from relloc.events import Event, OdometryEvent, RangeEvent
from relloc.localizer import Estimate
from relloc.sinks.zenoh_sink import ZenohSink, pose_key
from relloc.sources.zenoh_source import (
    Arrival,
    ZenohSource,
    ZenohSourceOptions,
    build_routes,
    encode_sent_time,
    key_for_topic,
)

__all__ = [
    "EstimateCollector",
    "LiveServer",
    "PublishStats",
    "ReplayOptions",
    "ServeOptions",
    "ZenohOptions",
    "add_zenoh_args",
    "ape_against_bag",
    "event_messages",
    "free_tcp_port",
    "open_session",
    "publish_events",
    "register",
    "replay_bag",
    "simulated_team",
    "zenoh_options_from_args",
]

log = logging.getLogger(__name__)

DETECTION_METHODS = ("pf_uv", "pf_ulv")
"""Methods that use cooperative detections: only they make the server subscribe to cameras."""

SHORTBAG = "multi4_shortbag_20221011"

SIM_TIME_BASE = 1_700_000_000.0
"""Added to the simulator's stamps when they go on the wire (a fixed value keeps runs
reproducible; zero stamps would mean "no stamp")."""


# ============================================================================ Zenoh sessions
@dataclass(frozen=True)
class ZenohOptions:
    """How to open a Zenoh session: mode, endpoints, scouting, or a full config file."""

    mode: Literal["peer", "client"] = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast: bool = True
    """Multicast scouting (finding peers on the LAN); off for tests and loopback benchmarks."""
    config_file: Path | None = None
    """A Zenoh JSON5 config; the options above are applied on top of it."""

    def to_config(self) -> Any:
        """The ``zenoh.Config``."""
        import zenoh

        config = (
            zenoh.Config.from_file(str(self.config_file)) if self.config_file else zenoh.Config()
        )
        config.insert_json5("mode", json.dumps(self.mode))
        if self.connect:
            config.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.listen:
            config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        if not self.multicast:
            config.insert_json5("scouting/multicast/enabled", "false")
        return config


def open_session(options: ZenohOptions) -> Any:
    """Open a ``zenoh.Session`` (the caller closes it)."""
    import zenoh

    return zenoh.open(options.to_config())


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for loopback tests and benchmarks)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ============================================================================ serve
@dataclass(frozen=True)
class ServeOptions:
    """What ``relloc serve`` runs and how it talks."""

    methods: tuple[str, ...] = ("pf",)
    seed: int = 0
    particles: int | None = None
    models: Path | None = None
    prefix: str = ""
    """Key prefix of the robots' topics (the bridge's namespace)."""
    out_prefix: str = "relloc"
    """Key prefix of what the server publishes."""
    reorder_window: float = 0.0
    """Reorder-buffer window (s of header time); 0: lowest latency (see ``docs/live.md``)."""
    clock_rate: float = 1.0
    """Header seconds per wall second: pair with ``relloc replay --rate``."""
    status_period: float = 1.0
    trace: bool = False
    subscribe_all: bool = False
    quiet_after: float = 2.0
    """A robot silent this long (s) is reported as quiet in the status."""
    keep_estimates: int = 2000
    """Estimates kept per pipeline in memory (the engine keeps all; a server runs for hours)."""


class LiveServer:
    """The engine, fed by a Zenoh source, publishing through a Zenoh sink.

    ``start`` declares the subscribers; ``run`` is the engine loop (on the calling thread) until
    :meth:`stop` or ``duration``; ``close`` undeclares everything. The session belongs to the
    caller. Any exception of the engine on one event is logged and counted
    (``engine_errors``), never allowed to stop the server.
    """

    def __init__(
        self, config: TeamConfig, session: Any, options: ServeOptions | None = None
    ) -> None:
        from relloc.methods import build_pipeline

        self.options = opts = options or ServeOptions()
        if not opts.methods:
            raise ValueError("serve needs at least one method")
        if opts.particles:
            config = config.with_filter(particles=opts.particles)
        self.config = config
        self.session = session
        self.pipelines: list[Pipeline] = [
            build_pipeline(m, config, seed=opts.seed, models=opts.models) for m in opts.methods
        ]
        self.source = ZenohSource(
            config,
            ZenohSourceOptions(
                prefix=opts.prefix,
                reorder_window=opts.reorder_window,
                clock_rate=opts.clock_rate,
                detections=any(m in DETECTION_METHODS for m in opts.methods),
                subscribe_all=opts.subscribe_all,
            ),
        )
        self.sink = ZenohSink(
            session,
            config,
            prefix=opts.out_prefix,
            primary_method=opts.methods[0],
            trace=opts.trace,
        )
        self.engine = Engine(
            self.pipelines, config.reference, [self.sink], keep_estimates=opts.keep_estimates
        )
        self.engine_errors = 0
        self.engine_thread_cpu_s = 0.0
        """CPU time of the thread that ran :meth:`run` (the rest is Zenoh's threads)."""
        self.started = time.time()
        self._stopping = False
        self._quiet: set[str] = set()
        self._last_counts: tuple[float, dict[str, int]] = (self.started, {})

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Subscribe to the team's keys."""
        self.source.attach(self.session)
        self.started = time.time()
        self._last_counts = (self.started, self._counts())

    def stop(self) -> None:
        """Ask :meth:`run` to finish (safe from any thread and from a signal handler)."""
        self._stopping = True  # a plain store: no lock a signal handler could deadlock on
        self.source.wake()  # SimpleQueue.put is reentrant: fine in a signal handler

    def close(self) -> None:
        """Undeclare subscribers and publishers (the session stays open)."""
        self.source.detach()
        self.sink.close()

    def run(self, duration: float | None = None) -> dict[str, Any]:
        """Process messages until :meth:`stop` or ``duration`` seconds; returns :meth:`summary`.

        At the end, what is queued or held is processed, the pending batch is fused (one last
        estimate) and a final status is published.
        """
        cpu_start = time.thread_time()
        now = time.time()
        deadline = math.inf if duration is None else now + duration
        period = self.options.status_period
        next_status = now + period
        while not self._stopping:
            now = time.time()
            if now >= deadline:
                break
            timeout = max(0.0, min(0.2, next_status - now, deadline - now))
            self.feed(self.source.poll(timeout))
            now = time.time()
            if now >= next_status:
                self._publish_status(now)
                next_status = max(next_status + period, now + 0.5 * period)
        self.feed(self.source.drain())
        try:
            self.engine.finish()
        except Exception:
            self.engine_errors += 1
            log.exception("the engine failed while finishing")
        self._publish_status(time.time())
        self.engine_thread_cpu_s += time.thread_time() - cpu_start
        return self.summary()

    def feed(self, arrivals: Iterable[Arrival]) -> None:
        """Run the engine on released events (what :meth:`run` does with each poll)."""
        for arrival in arrivals:
            self.sink.set_trigger(arrival)
            try:
                self.engine.feed(arrival.event)
            except Exception:
                self.engine_errors += 1
                log.exception("the engine failed on %r; skipped", arrival.event)
        self.sink.set_trigger(None)

    # ------------------------------------------------------------------ status
    def _counts(self) -> dict[str, int]:
        st = self.source.stats
        counts = {"messages": sum(st.received.values())}
        counts.update({f"event.{k}": v for k, v in st.events.items()})
        counts.update({f"estimate.{p.name}": self.sink.published[p.name] for p in self.pipelines})
        return counts

    def _publish_status(self, now: float) -> None:
        status = self.status(now)
        try:
            self.sink.publish_status(status)
        except Exception as exc:  # a closed session at shutdown: the status is not vital
            log.warning("could not publish the status: %s", exc)

    def status(self, now: float | None = None) -> dict[str, Any]:
        """The status published on ``<prefix>/status`` (rates since the previous call)."""
        now = time.time() if now is None else now
        then, before = self._last_counts
        counts = self._counts()
        dt = max(now - then, 1e-9)
        self._last_counts = (now, counts)

        def rate(name: str) -> float:
            return round((counts.get(name, 0) - before.get(name, 0)) / dt, 2)

        st = self.source.stats
        robots: dict[str, Any] = {}
        for r in self.config.robot_names:
            last = st.last_received.get(r)
            age = None if last is None else round(now - last, 3)
            quiet = age is None or age > self.options.quiet_after
            if quiet and last is not None and r not in self._quiet:
                log.warning("%s has been quiet for %.1f s", r, age)
            if not quiet and r in self._quiet:
                log.warning("%s publishes again", r)
            if quiet and last is not None:
                self._quiet.add(r)
            else:
                self._quiet.discard(r)
            robots[r] = {"last_message_age_s": age, "quiet": quiet}
        methods: dict[str, Any] = {}
        for p in self.pipelines:
            last_est = self.sink.last.get(p.name)
            methods[p.name] = {
                "estimates": self.sink.published[p.name],
                "rate_hz": rate(f"estimate.{p.name}"),
                "last_estimate_t": None if last_est is None else last_est.t,
                "ess": None if last_est is None or last_est.ess is None else round(last_est.ess, 1),
                "rejected": dict(p.localizer.rejected),
                "compute_s": round(p.compute_s, 4),
                "stats": {k: v for k, v in p.stats().items() if not k.startswith("rejected_")},
            }
        return {
            "time": now,
            "uptime_s": round(now - self.started, 3),
            "team": self.config.name,
            "reference": self.config.reference,
            "particles": self.config.filter.particles,
            "methods": methods,
            "source": {
                "messages": counts["messages"],
                "rate_hz": rate("messages"),
                "events_rate_hz": {
                    k: rate(f"event.{k}") for k in ("odometry", "range", "detection")
                },
                "rejected": dict(st.rejected),
                "out_of_order": st.out_of_order,
                "restamped": sum(st.restamped.values()),
                "queue_depth": self.source.queue_depth,
                "buffer_depth": len(self.source.buffer),
            },
            "robots": robots,
            "engine_errors": self.engine_errors,
        }

    def summary(self) -> dict[str, Any]:
        """Final figures: the status plus the totals of the run."""
        status = self.status()
        status["source"]["stats"] = self.source.stats.as_dict()
        status["events"] = self.engine.events
        status["engine_thread_cpu_s"] = round(self.engine_thread_cpu_s, 3)
        status["header_time_span_s"] = (
            None
            if self.engine.t_first is None or self.engine.t_last is None
            else round(self.engine.t_last - self.engine.t_first, 3)
        )
        return status


# ============================================================================ publishing data
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


class _Publishers:
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
    pubs: _Publishers,
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
    pubs = _Publishers(session)
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
    from relloc.sources.simulator import multi_scenario

    sim = multi_scenario(seed, duration=duration)
    config = sim.config
    for robot in config.robot_names:
        config = config.with_robot(robot, odom_topic=f"/{robot}/odom")
    return sim, config


def event_messages(
    events: Iterable[Event], config: TeamConfig, *, prefix: str = "", time_base: float = 0.0
) -> Iterator[tuple[float, str, bytes]]:
    """Relloc events as the ROS 2 messages a team would publish: ``(t, key, CDR payload)``.

    Odometry becomes ``nav_msgs/Odometry`` on the robot's odometry key, a range
    ``sensor_msgs/Range`` on the key of its node pair (in the event's node order); other events
    are skipped. ``time_base`` is added to every header stamp (the simulator starts at 0, and a
    zero stamp means "no stamp" on the wire); ``t`` stays the event's own time.
    """
    from relloc.ros_messages import encode, odometry_msg, range_msg

    routes = build_routes(config, prefix=prefix, detections=False)
    odom_keys = {r.robot: k for k, r in routes.items() if r.kind == "odometry"}
    range_keys: dict[tuple[str, str], str] = {}
    for k, r in routes.items():
        if r.kind == "range":
            range_keys.setdefault((r.node_a, r.node_b), k)
    for ev in events:
        if isinstance(ev, OdometryEvent) and ev.robot in odom_keys:
            yield ev.t, odom_keys[ev.robot], encode(odometry_msg(replace(ev, t=ev.t + time_base)))
        elif isinstance(ev, RangeEvent):
            key = range_keys.get((ev.node_a, ev.node_b))
            if key is not None:
                yield ev.t, key, encode(range_msg(replace(ev, t=ev.t + time_base)))


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
    pubs = _Publishers(session)
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


# ============================================================================ collecting estimates
class EstimateCollector:
    """Subscribes to a server's pose (and trace) keys and rebuilds the estimates it published.

    For tests and benchmarks: the same messages any ROS consumer would get. Messages are decoded
    on Zenoh's threads into lists guarded by a lock.
    """

    def __init__(
        self,
        session: Any,
        config: TeamConfig,
        *,
        prefix: str = "relloc",
        method: str = "pf",
        primary: bool = True,
    ) -> None:
        self.config = config
        self.method = method
        self._lock = threading.Lock()
        self._poses: list[
            tuple[int, int, str, float, float, tuple[float, float, float, float]]
        ] = []
        self._traces: list[dict[str, Any]] = []
        expr = pose_key(prefix, "*", None if primary else method)
        self._subs = [
            session.declare_subscriber(expr, self._on_pose),
            session.declare_subscriber(f"{prefix.strip('/')}/trace", self._on_trace),
        ]

    def _on_pose(self, sample: Any) -> None:
        from relloc.ros_messages import POSE_WITH_COVARIANCE_STAMPED, decode

        robot = str(sample.key_expr).split("/")[-2]
        msg = decode(sample.payload.to_bytes(), POSE_WITH_COVARIANCE_STAMPED)
        c = msg.pose.covariance
        p = msg.pose.pose.position
        item = (
            int(msg.header.stamp.sec),
            int(msg.header.stamp.nanosec),
            robot,
            float(p.x),
            float(p.y),
            (float(c[0]), float(c[1]), float(c[6]), float(c[7])),
        )
        with self._lock:
            self._poses.append(item)

    def _on_trace(self, sample: Any) -> None:
        record = json.loads(sample.payload.to_bytes())
        record["received"] = time.time()
        with self._lock:
            self._traces.append(record)

    def estimates(self) -> list[Estimate]:
        """The published estimates, one per stamp, in time order."""
        with self._lock:
            poses = list(self._poses)
        grouped: dict[tuple[int, int], dict[str, Any]] = {}
        for sec, nsec, robot, x, y, cov in poses:
            grouped.setdefault((sec, nsec), {})[robot] = (x, y, cov)
        out = []
        for (sec, nsec), robots in sorted(grouped.items()):
            out.append(
                Estimate(
                    t=sec + nsec * 1e-9,
                    method=self.method,
                    reference=self.config.reference,
                    positions={r: (v[0], v[1]) for r, v in robots.items()},
                    covariances={
                        r: ((v[2][0], v[2][1]), (v[2][2], v[2][3])) for r, v in robots.items()
                    },
                )
            )
        return out

    def traces(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self._traces)

    def close(self) -> None:
        subs, self._subs = self._subs, []
        for sub in subs:
            try:
                sub.undeclare()
            except Exception as exc:
                log.debug("undeclaring a subscriber failed: %s", exc)


def ape_against_bag(
    estimates: list[Estimate],
    bag: Path,
    config: TeamConfig,
    *,
    warmup: float = 5.0,
    t0: float | None = None,
) -> dict[str, Any]:
    """APE of estimates against the motion capture of a bag (the ``relloc run`` definition).

    ``t0`` is the start of the warm-up window (default: the bag's first motion-capture stamp).
    Returns per robot ``{"median", "rmse", "max", "n"}`` and ``"mean_median"``.
    """
    from relloc.events import GroundTruthEvent
    from relloc.sinks.metrics import ApeStats, GroundTruth, after, associate
    from relloc.sources.rosbag import RosbagSource

    gt = GroundTruth(config.reference)
    source = RosbagSource(bag, config, detections=False, ranges=False, odometry=False)
    first = None
    for ev in source:
        if isinstance(ev, GroundTruthEvent):
            first = ev.t if first is None else first
            gt.add(ev)
    start = (t0 if t0 is not None else (first or 0.0)) + warmup
    paired = associate(estimates, gt, config.others)
    out: dict[str, Any] = {}
    medians = []
    for robot, p in paired.items():
        s = ApeStats.of(after(p, start).errors)
        out[robot] = {"median": s.median, "rmse": s.rmse, "max": s.max, "n": s.n}
        if s.n:
            medians.append(s.median)
    out["mean_median"] = statistics.fmean(medians) if medians else math.nan
    return out


# ============================================================================ command line
def add_zenoh_args(p: argparse.ArgumentParser) -> None:
    """The Zenoh session options of every live command (``--mode``, ``--connect``, ...)."""
    g = p.add_argument_group("zenoh")
    g.add_argument("--mode", choices=("peer", "client"), default="peer")
    g.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="EP",
        help="e.g. tcp/192.168.1.10:7447 (repeatable)",
    )
    g.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="EP",
        help="e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    g.add_argument("--no-multicast", action="store_true", help="disable multicast scouting")
    g.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE",
        help="a Zenoh JSON5 config (the options above override it)",
    )
    g.add_argument(
        "--prefix", default="", help="key prefix of the robots' topics (the bridge namespace)"
    )


def zenoh_options_from_args(args: argparse.Namespace) -> ZenohOptions:
    """The :class:`ZenohOptions` of arguments added by :func:`add_zenoh_args`."""
    return ZenohOptions(
        mode=args.mode,
        connect=tuple(args.connect),
        listen=tuple(args.listen),
        multicast=not args.no_multicast,
        config_file=Path(args.zenoh_config) if args.zenoh_config else None,
    )


# Names used before these two became public (relloc.navigation.cli imports them).


def _open_cli_session(args: argparse.Namespace) -> Any:
    """The session of a command, or a one-line error (e.g. the --listen port is taken)."""
    from relloc.cli import UserError

    try:
        return open_session(zenoh_options_from_args(args))
    except Exception as exc:  # zenoh.ZError and config errors
        raise UserError(f"cannot open a Zenoh session: {exc}") from None


def check_positive(**values: float) -> None:
    from relloc.cli import UserError

    for name, value in values.items():
        if not value > 0:
            raise UserError(f"--{name.replace('_', '-')} must be positive, got {value}")


def _cmd_serve(args: argparse.Namespace) -> int:
    from relloc.cli import UserError
    from relloc.methods import parse_methods

    check_positive(clock_rate=args.clock_rate, status_period=args.status_period)
    if args.reorder_window < 0:
        raise UserError(f"--reorder-window must be >= 0, got {args.reorder_window}")
    config = TeamConfig.load(args.config)
    opts = ServeOptions(
        methods=tuple(parse_methods(args.methods)),
        seed=args.seed,
        particles=args.particles,
        models=Path(args.models) if args.models else None,
        prefix=args.prefix,
        out_prefix=args.out_prefix,
        reorder_window=args.reorder_window,
        clock_rate=args.clock_rate,
        status_period=args.status_period,
        trace=args.trace,
        subscribe_all=args.subscribe_all,
    )
    session = _open_cli_session(args)
    try:
        server = LiveServer(config, session, opts)
    except Exception:
        session.close()
        raise
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, lambda *_: server.stop())
    try:
        server.start()
        print(
            f"relloc serve: {config.name}, {', '.join(opts.methods)}, "
            f"{server.config.filter.particles} particles; {len(server.source.keys)} keys in, "
            f"estimates on {server.sink.key('<robot>', opts.methods[0])}",
            flush=True,
        )
        summary = server.run(args.duration)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        server.close()
        session.close()
    _print_summary(summary)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(summary, indent=2))
    return 0


def _print_summary(s: dict[str, Any]) -> None:
    src = s["source"]
    print(f"stopped after {s['uptime_s']:.1f} s: {src['messages']} messages, {s['events']} events")
    print(f"  source rejected: {src['rejected'] or 'nothing'}; out of order: {src['out_of_order']}")
    for name, m in s["methods"].items():
        print(
            f"  {name}: {m['estimates']} estimates, last at t={m['last_estimate_t']}, ESS {m['ess']}, "
            f"compute {m['compute_s']:.2f} s, rejected {m['rejected'] or 'nothing'}"
        )
    if s["engine_errors"]:
        print(f"  engine errors: {s['engine_errors']} (see the log)")


def _cmd_replay(args: argparse.Namespace) -> int:
    check_positive(rate=args.rate)
    config = TeamConfig.load(args.config)
    opts = ReplayOptions(
        rate=args.rate,
        prefix=args.prefix,
        team_only=args.team_only,
        ground_truth=args.ground_truth,
        wait=args.wait,
        start=args.start,
        duration=args.duration,
    )
    session = _open_cli_session(args)
    stopping = False

    def request_stop(*_: Any) -> None:
        nonlocal stopping
        stopping = True

    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, request_stop)
    try:
        stats = replay_bag(Path(args.bag), config, session, opts, stop=lambda: stopping)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        session.close()
    d = stats.as_dict()
    print(
        f"replayed {d['messages']} messages on {d['keys']} keys in {d['wall_s']:.1f} s "
        f"(rate {opts.rate:g}, at worst {1e3 * stats.max_behind_s:.1f} ms behind schedule)"
    )
    if stats.unmatched:
        print(f"  no subscriber when it started: {', '.join(stats.unmatched)}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``serve``, ``replay`` and ``bench`` to the ``relloc`` command line."""
    serve = sub.add_parser(
        "serve", help="run the localizer live on Zenoh (ROS 2 topics via a bridge)"
    )
    serve.add_argument("--config", required=True, help="team config (TOML)")
    serve.add_argument(
        "--methods",
        default="pf",
        help="comma-separated; the first one is published on relloc/<robot>/pose",
    )
    serve.add_argument("--seed", type=int, default=0)
    serve.add_argument(
        "--particles", type=int, default=None, help="override the config's particle count"
    )
    serve.add_argument("--models", default=None, help="trained range-error models (for pf_ul)")
    serve.add_argument(
        "--out-prefix", default="relloc", help="key prefix of the estimates and status"
    )
    serve.add_argument("--reorder-window", type=float, default=0.0, metavar="S",
                       help="hold events up to S s of header time to put them in order (adds S s of latency)")  # fmt: skip
    serve.add_argument("--clock-rate", type=float, default=1.0,
                       help="header seconds per wall second (match relloc replay --rate)")  # fmt: skip
    serve.add_argument("--status-period", type=float, default=1.0, metavar="S")
    serve.add_argument(
        "--trace",
        action="store_true",
        help="publish a latency trace per estimate on <out-prefix>/trace",
    )
    serve.add_argument(
        "--subscribe-all",
        action="store_true",
        help="subscribe to <prefix>/** (unknown keys are counted)",
    )
    serve.add_argument(
        "--duration", type=float, default=None, metavar="S", help="stop after S seconds"
    )
    serve.add_argument(
        "--json", default=None, metavar="FILE", help="write the final figures as JSON"
    )
    add_zenoh_args(serve)
    serve.set_defaults(handler=_cmd_serve)

    replay = sub.add_parser(
        "replay", help="publish a rosbag2 recording on Zenoh as the robots would"
    )
    replay.add_argument("bag", help="bag folder (metadata.yaml) or .db3/.mcap file")
    replay.add_argument(
        "--config", required=True, help="team config (TOML): keys of the team's topics"
    )
    replay.add_argument("--rate", type=float, default=1.0, help="speed factor (2: twice as fast)")
    replay.add_argument("--team-only", action="store_true", help="publish only the team's topics")
    replay.add_argument(
        "--ground-truth", action="store_true", help="also publish motion capture (mocap_topic)"
    )
    replay.add_argument(
        "--wait",
        type=float,
        default=10.0,
        metavar="S",
        help="wait up to S s for the server's subscribers",
    )
    replay.add_argument("--start", type=float, default=0.0, metavar="S", help="skip S s of the bag")
    replay.add_argument("--duration", type=float, default=None, metavar="S")
    add_zenoh_args(replay)
    replay.set_defaults(handler=_cmd_replay)
