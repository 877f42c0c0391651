"""Navigation and simulated robots over Eclipse Zenoh (``relloc navigate``, ``relloc sim-robots``).

Keys follow zenoh-bridge-ros2dds, as everywhere in relloc (:func:`relloc.sources.zenoh_source.key_for_topic`):
a ROS topic ``/tb1/odom`` is the key ``tb1/odom``, below the global ``--prefix`` and the robot's
``zenoh_scope``; payloads are ROS 2 CDR. So a TurtleBot 4 behind the bridge needs no change:

=================================  =========================================  ===============
key                                message                                    who publishes
=================================  =========================================  ===============
``<robot>/odom``                   ``nav_msgs/Odometry``                      robot / sim-robots
``uwb/tof/<a>/<b>/distance``       ``sensor_msgs/Range``                      robot / sim-robots
``relloc/<robot>/pose``            ``geometry_msgs/PoseWithCovarianceStamped``  ``relloc serve``
``<robot>/cmd_vel``                ``geometry_msgs/Twist``                    ``relloc navigate``
``vrpn_client_node/<body>/pose``   ``geometry_msgs/PoseStamped`` (truth)      sim-robots only
=================================  =========================================  ===============

``relloc navigate``
    :class:`LiveNavigation` subscribes to the robot's odometry (its heading in the shared frame,
    and the clock) and to the estimate ``relloc serve`` publishes for it, or, with
    ``--in-process``, runs the server (:class:`relloc.live.LiveServer`) on its own session and
    takes the estimates straight from the engine. A :class:`NavigationLoop` then publishes a
    ``Twist`` at the control rate: the :class:`~relloc.navigation.navigator.Navigator`'s command,
    zero while the safety gate holds the robot, and zero (three times) when it stops for good
    (path complete, Ctrl-C, SIGTERM, ``--duration``).
``relloc sim-robots``
    :class:`SimRobots` runs a simulated team (:mod:`relloc.sources.simulator`) in real time
    (times ``--rate``) and publishes its odometry, UWB ranges and motion capture as the real
    robots would; commanded robots obey ``cmd_vel`` (and stop when no command has come for
    ``cmd_timeout`` seconds, as a robot base does). With it, ``relloc serve`` and
    ``relloc navigate`` run the whole live system on one machine.

Clocks
------
Estimates and odometry carry header stamps (robot time). The navigator's "now" is
:class:`DataClock`: the newest odometry stamp of the robot plus the wall time since it arrived
(times the clock rate). Ages are therefore measured on the robots' clock, whatever the offset
of this machine's clock, and keep growing when the data stops (so the gate stops the robot).
With ``--rate R`` on sim-robots, give ``--clock-rate R`` to serve and navigate: everything,
the control period included, then runs R times faster, consistently.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from relloc.config import RobotConfig, TeamConfig
from relloc.estimate import Estimate
from relloc.events import GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.navigation.controller import Command, ControllerConfig
from relloc.navigation.navigator import Navigator
from relloc.navigation.path import WaypointPath
from relloc.navigation.safety import SafetyConfig
from relloc.ros_messages import (
    ODOMETRY,
    POSE_STAMPED,
    POSE_WITH_COVARIANCE_STAMPED,
    TWIST,
    MessageDecodeError,
    decode,
    encode,
    odometry_msg,
    odometry_to_event,
    quaternion_from_yaw,
    range_msg,
    stamp_to_sec,
    time_msg,
    twist_msg,
    typestore,
)
from relloc.sources.zenoh_source import build_routes, key_for_topic

__all__ = [
    "DataClock",
    "LiveNavigation",
    "NavigateOptions",
    "NavigationLoop",
    "SimRobots",
    "SimRobotsOptions",
    "cmd_vel_key",
    "decode_estimate",
    "odom_key",
    "pose_stamped_msg",
    "save_json",
    "sim_team_config",
]

log = logging.getLogger("relloc.navigation")


# ============================================================================ keys and messages
def cmd_vel_key(robot: RobotConfig, prefix: str = "") -> str:
    """The key of a robot's velocity commands: ``cmd_vel_topic`` (default ``/<robot>/cmd_vel``)
    under the bridge convention, e.g. ``tb1/cmd_vel``."""
    topic = robot.cmd_vel_topic or f"/{robot.name}/cmd_vel"
    return key_for_topic(topic, prefix=prefix, scope=robot.zenoh_scope)


def odom_key(robot: RobotConfig, prefix: str = "") -> str:
    """The key of a robot's odometry (its ``odom_topic``, default ``/<robot>/odom``)."""
    topic = robot.odom_topic or f"/{robot.name}/odom"
    return key_for_topic(topic, prefix=prefix, scope=robot.zenoh_scope)


def decode_estimate(payload: bytes, robot: str, reference: str, method: str = "pf") -> Estimate:
    """A ``PoseWithCovarianceStamped`` published by ``relloc serve`` as a one-robot estimate."""
    msg = decode(payload, POSE_WITH_COVARIANCE_STAMPED)
    c = msg.pose.covariance
    p = msg.pose.pose.position
    return Estimate(
        t=stamp_to_sec(msg.header.stamp),
        method=method,
        reference=msg.header.frame_id or reference,
        positions={robot: (float(p.x), float(p.y))},
        covariances={robot: ((float(c[0]), float(c[1])), (float(c[6]), float(c[7])))},
    )


def pose_stamped_msg(t: float, x: float, y: float, yaw: float, frame_id: str = "world") -> Any:
    """A ``geometry_msgs/PoseStamped`` (what a motion-capture bridge publishes)."""
    types = typestore().types
    header = types["std_msgs/msg/Header"](stamp=time_msg(t), frame_id=frame_id)
    point = types["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0)
    pose = types["geometry_msgs/msg/Pose"](position=point, orientation=quaternion_from_yaw(yaw))
    return types[POSE_STAMPED](header=header, pose=pose)


# ============================================================================ clock
class DataClock:
    """The robots' clock, read on this machine: last odometry stamp + scaled wall time since."""

    def __init__(self, rate: float = 1.0, wall: Callable[[], float] = time.time) -> None:
        if not rate > 0:
            raise ValueError(f"clock rate must be positive, got {rate}")
        self.rate = rate
        self.wall = wall
        self._stamp: float | None = None
        self._received = 0.0
        self._lock = threading.Lock()

    def observe(self, stamp: float) -> None:
        """A message stamped ``stamp`` has just arrived."""
        with self._lock:
            if self._stamp is None or stamp >= self._stamp:
                self._stamp, self._received = stamp, self.wall()

    def now(self) -> float | None:
        """Current data time, or ``None`` before the first message."""
        with self._lock:
            if self._stamp is None:
                return None
            return self._stamp + self.rate * (self.wall() - self._received)


# ============================================================================ control loop
class NavigationLoop:
    """Runs a :class:`Navigator` at its control rate and publishes each command.

    ``publish(v, w)`` sends a command (a ``Twist`` on ``cmd_vel`` live, ``set_command`` in
    tests); ``now()`` gives the data time (``None`` before any odometry). Navigator calls are
    serialised with :attr:`lock`, which the data callbacks also take. :meth:`run` returns when
    the navigator finishes, when ``stop`` is set (Ctrl-C, SIGTERM: an immediate zero command
    and a terminal stop), on ``KeyboardInterrupt`` (the same), or after ``duration`` wall
    seconds.
    """

    def __init__(
        self,
        navigator: Navigator,
        publish: Callable[[float, float], None],
        now: Callable[[], float | None],
        *,
        clock_rate: float = 1.0,
        zero_repeats: int = 3,
    ) -> None:
        self.navigator = navigator
        self.publish = publish
        self.now = now
        self.period = navigator.follower.config.period / clock_rate
        """Wall seconds between two commands."""
        self.lock = threading.Lock()
        self.zero_repeats = zero_repeats
        self.commands: list[tuple[float, Command]] = []
        """Every command published, with the wall time it went out."""
        self.stop_reason: str | None = None

    def tick(self) -> Command:
        """Compute and publish one command."""
        with self.lock:
            now = self.now()
            nav = self.navigator
            if now is None:
                # No odometry yet: no clock, no heading. Hold, on the estimate's clock if any.
                t = nav.estimate.t if nav.estimate is not None else 0.0
                cmd = nav.update(t)
            else:
                cmd = nav.update(now)
        self._send(cmd)
        return cmd

    def halt(self, reason: str, detail: str = "") -> Command:
        """Terminal stop: zero command now (repeated, in case one is lost)."""
        with self.lock:
            now = self.now()
            nav = self.navigator
            t = now if now is not None else (nav.estimate.t if nav.estimate else 0.0)
            cmd = nav.interrupt(t, reason, detail)
        self.stop_reason = reason
        for _ in range(max(self.zero_repeats, 1)):
            self._send(cmd)
        return cmd

    def run(self, stop: threading.Event | None = None, duration: float | None = None) -> str:
        """Control until finished; returns why it ended (``"goal reached"``, ``"interrupted"``,
        ``"duration"``)."""
        stop = stop or threading.Event()
        start = time.monotonic()
        next_tick = start
        try:
            while True:
                if stop.is_set():
                    self.halt("interrupted", "stopped by the operator (signal)")
                    break
                if duration is not None and time.monotonic() - start >= duration:
                    self.halt("duration", f"--duration of {duration:g} s elapsed")
                    break
                cmd = self.tick()
                if self.navigator.finished:
                    for _ in range(self.zero_repeats - 1):
                        self._send(cmd)
                    self.stop_reason = self.navigator.gate.terminal
                    break
                next_tick += self.period
                delay = next_tick - time.monotonic()
                if delay < -self.period:  # fell far behind (suspended?): do not burst
                    next_tick = time.monotonic()
                    delay = 0.0
                stop.wait(max(delay, 0.0))
        except KeyboardInterrupt:
            self.halt("interrupted", "Ctrl-C")
        return self.stop_reason or "stopped"

    def _send(self, cmd: Command) -> None:
        try:
            self.publish(cmd.v, cmd.w)
        except Exception as exc:  # a closed session at shutdown must not hide the stop
            log.warning("could not publish a command: %s", exc)
        self.commands.append((time.time(), cmd))


# ============================================================================ navigate
@dataclass(frozen=True)
class NavigateOptions:
    """What ``relloc navigate`` does."""

    robot: str
    path: WaypointPath
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    prefix: str = ""
    """Key prefix of the robots' topics (the bridge's namespace)."""
    estimate_prefix: str = "relloc"
    """Key prefix of the estimates (``relloc serve --out-prefix``)."""
    clock_rate: float = 1.0
    in_process: bool = False
    """Run the localizer in this process instead of subscribing to ``relloc serve``."""
    methods: tuple[str, ...] = ("pf",)
    seed: int = 0
    particles: int | None = None
    latency_compensation: bool = True
    duration: float | None = None


class LiveNavigation:
    """Subscriptions, publisher and control loop of ``relloc navigate`` on one session."""

    def __init__(self, config: TeamConfig, session: Any, options: NavigateOptions) -> None:
        self.config = config
        self.session = session
        self.options = opts = options
        robot = config.robot(opts.robot)  # KeyError names the team
        if opts.robot == config.reference:
            raise ValueError(
                f"{opts.robot} is the reference robot: its relative position is (0, 0) by "
                "definition; navigate another robot"
            )
        if opts.path.reference and opts.path.reference != config.reference:
            from relloc.navigation.path import PathError

            raise PathError(
                f"path {opts.path.name!r} is relative to {opts.path.reference!r}, the team's "
                f"reference is {config.reference!r}"
            )
        self.robot = robot
        self.navigator = Navigator(
            opts.path,
            robot,
            controller=opts.controller,
            safety=opts.safety,
            latency_compensation=opts.latency_compensation,
            max_odom_extrapolation=config.filter.odometry.max_odom_extrapolation,
        )
        self.clock = DataClock(opts.clock_rate)
        self.cmd_key = cmd_vel_key(robot, opts.prefix)
        self.odom_key = odom_key(robot, opts.prefix)
        from relloc.sinks.zenoh_sink import pose_key

        self.pose_key = pose_key(opts.estimate_prefix, robot.name)
        self._cmd_pub = session.declare_publisher(self.cmd_key)
        self.loop = NavigationLoop(
            self.navigator, self._publish, self.clock.now, clock_rate=opts.clock_rate
        )
        self.received = {"odometry": 0, "estimate": 0, "decode_error": 0}
        self.t0: float | None = None
        """Stamp of the first odometry message (the printed times are relative to it)."""
        self._subs: list[Any] = []
        self.server: Any = None
        self._server_thread: threading.Thread | None = None

    # ---------------------------------------------------------------- zenoh side
    def start(self) -> None:
        """Declare subscribers (and start the in-process server)."""
        self._subs.append(self.session.declare_subscriber(self.odom_key, self._on_odom))
        if self.options.in_process:
            from relloc.live import LiveServer, ServeOptions

            opts = self.options
            self.server = LiveServer(
                self.config,
                self.session,
                ServeOptions(
                    methods=opts.methods,
                    seed=opts.seed,
                    particles=opts.particles,
                    prefix=opts.prefix,
                    out_prefix=opts.estimate_prefix,
                    clock_rate=opts.clock_rate,
                ),
            )
            self.server.engine.sinks.append(self._on_engine_estimate)
            self.server.start()
            self._server_thread = threading.Thread(
                target=self.server.run, name="relloc-engine", daemon=True
            )
            self._server_thread.start()
        else:
            self._subs.append(self.session.declare_subscriber(self.pose_key, self._on_pose))

    def close(self) -> None:
        """Stop the in-process server, undeclare everything (the session stays open)."""
        if self.server is not None:
            self.server.stop()
            if self._server_thread is not None:
                self._server_thread.join(timeout=10)
            self.server.close()
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception as exc:
                log.debug("undeclaring a subscriber failed: %s", exc)
        self._subs = []
        try:
            self._cmd_pub.undeclare()
        except Exception as exc:
            log.debug("undeclaring the cmd_vel publisher failed: %s", exc)

    def _publish(self, v: float, w: float) -> None:
        self._cmd_pub.put(encode(twist_msg(v, w)))

    def _on_odom(self, sample: Any) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), ODOMETRY)
        except MessageDecodeError as exc:
            self.received["decode_error"] += 1
            log.warning("undecodable odometry on %s: %s", self.odom_key, exc)
            return
        stamp = stamp_to_sec(msg.header.stamp)
        if stamp == 0.0 or self.robot.odom_zero_stamps:
            stamp = self.clock.now() or time.time()
            stamp = max(stamp, self.navigator.track.last_time + 1e-3)
        event = odometry_to_event(msg, self.robot.name, t=stamp)
        if self.t0 is None:
            self.t0 = stamp
        with self.loop.lock:
            self.navigator.on_odometry(event)
        self.clock.observe(stamp)
        self.received["odometry"] += 1

    def _on_pose(self, sample: Any) -> None:
        try:
            est = decode_estimate(sample.payload.to_bytes(), self.robot.name, self.config.reference)
        except MessageDecodeError as exc:
            self.received["decode_error"] += 1
            log.warning("undecodable estimate on %s: %s", self.pose_key, exc)
            return
        with self.loop.lock:
            self.navigator.on_estimate(est)
        self.received["estimate"] += 1

    def _on_engine_estimate(self, est: Estimate) -> None:
        with self.loop.lock:
            self.navigator.on_estimate(est)
        self.received["estimate"] += 1

    # ---------------------------------------------------------------- run
    def run(self, stop: threading.Event | None = None) -> dict[str, Any]:
        """Control until the path is complete, ``stop`` is set or ``duration`` elapsed."""
        reason = self.loop.run(stop, self.options.duration)
        return self.summary(reason)

    def summary(self, reason: str) -> dict[str, Any]:
        """What happened: why it ended, the gate's stops, what was received and sent."""
        nav = self.navigator
        follower = nav.follower
        sent = self.loop.commands
        return {
            "robot": nav.robot,
            "path": nav.path.name,
            "ended": reason,
            "completed": nav.completed,
            "on_path": follower.on_path,
            "segment": follower.path_segment,
            "start_t": nav.start_time,
            "path_start_t": nav.path_start_time,
            "end_t": nav.gate.records[-1].t if nav.finished and nav.gate.records else None,
            "t0": self.t0,
            "stops": [
                {"t": s.t, "reason": s.reason, "detail": s.detail, "stop": s.stopped}
                for s in nav.gate.records
            ],
            "received": dict(self.received),
            "commands_sent": len(sent),
            "cmd_vel_key": self.cmd_key,
            "estimate_key": "(in process)" if self.options.in_process else self.pose_key,
        }


# ============================================================================ sim-robots
def sim_team_config(
    sim: Any, base: TeamConfig | None = None, particles: int | None = None
) -> TeamConfig:
    """The team config for a simulated team published over Zenoh.

    The simulator's own config (truthful calibration) with ROS topics: odometry on
    ``/<robot>/odom``, velocity commands on ``/<robot>/cmd_vel``, motion capture body = robot
    name. With ``base`` (a user's config for the same robot names) its topics, scopes and filter
    settings are used instead.
    """
    config: TeamConfig = sim.config
    if base is not None:
        missing = set(config.robot_names) - set(base.robot_names)
        if missing or base.reference != config.reference:
            raise ValueError(
                f"config {base.name!r} does not describe the simulated team: it needs robots "
                f"{list(config.robot_names)} with reference {config.reference!r}"
            )
        config = replace(
            config, filter=base.filter, uwb=replace(config.uwb, range_topic=base.uwb.range_topic)
        )
    for r in config.robots:
        own = base.robot(r.name) if base is not None else None
        config = config.with_robot(
            r.name,
            odom_topic=(own.odom_topic if own and own.odom_topic else f"/{r.name}/odom"),
            cmd_vel_topic=(
                own.cmd_vel_topic if own and own.cmd_vel_topic else f"/{r.name}/cmd_vel"
            ),
            zenoh_scope=own.zenoh_scope if own else "",
            mocap_body=(own.mocap_body if own and own.mocap_body else r.name),
        )
    if particles:
        config = config.with_filter(particles=particles)
    return config


@dataclass(frozen=True)
class SimRobotsOptions:
    """How ``relloc sim-robots`` runs the simulated team."""

    rate: float = 1.0
    """Simulated seconds per wall second."""
    step: float = 0.05
    """Simulation step (s of simulated time): commands are applied and data published per step."""
    prefix: str = ""
    cmd_timeout: float = 0.5
    """A commanded robot stops when no ``cmd_vel`` arrived for this long (simulated s)."""
    ground_truth: bool = True
    """Publish the true poses as motion capture (``mocap_topic``) for evaluation."""
    wait: float = 10.0
    """Wait up to this long (wall s) for a subscriber of the odometry and range keys."""
    time_base: float | None = None
    """Added to every stamp (default: the wall time at the start; stamps look like ROS time)."""
    duration: float | None = None
    """Stop after this many simulated seconds (default: the simulation's duration)."""


class SimRobots:
    """A simulated team on Zenoh: publishes its sensors, obeys ``cmd_vel``."""

    def __init__(
        self, sim: Any, config: TeamConfig, session: Any, options: SimRobotsOptions | None = None
    ) -> None:
        self.sim = sim
        self.config = config
        self.session = session
        self.options = opts = options or SimRobotsOptions()
        if not opts.rate > 0 or not opts.step > 0:
            raise ValueError("rate and step must be positive")
        routes = build_routes(config, prefix=opts.prefix, detections=False)
        self.odom_keys = {r.robot: k for k, r in routes.items() if r.kind == "odometry"}
        self.range_keys: dict[tuple[str, str], str] = {}
        for k, r in routes.items():
            if r.kind == "range":
                self.range_keys.setdefault((r.node_a, r.node_b), k)
        self.mocap_keys = {
            r.name: key_for_topic(
                config.mocap_topic.format(body=r.mocap_body or r.name), prefix=opts.prefix
            )
            for r in config.robots
        }
        self.cmd_keys = {
            name: cmd_vel_key(config.robot(name), opts.prefix) for name in sim.commanded
        }
        self._pubs: dict[str, Any] = {}
        self._subs: list[Any] = []
        self._lock = threading.Lock()
        self._commands: dict[str, tuple[float, float, float]] = {}  # robot -> (v, w, sim time)
        self.t_sim = 0.0
        self.time_base = 0.0
        self.published = 0
        self.commands_received = 0
        self.max_behind = 0.0
        self.truth: dict[str, list[tuple[float, float, float, float]]] = {n: [] for n in sim.robots}
        """True world poses ``(stamp, x, y, yaw)`` published, per robot."""

    def start(self) -> None:
        """Subscribe to the commanded robots' ``cmd_vel`` keys."""
        for robot, key in self.cmd_keys.items():
            self._subs.append(
                self.session.declare_subscriber(key, lambda s, robot=robot: self._on_cmd(robot, s))
            )

    def close(self) -> None:
        for ent in [*self._subs, *self._pubs.values()]:
            try:
                ent.undeclare()
            except Exception as exc:
                log.debug("undeclaring failed: %s", exc)
        self._subs, self._pubs = [], {}

    def _on_cmd(self, robot: str, sample: Any) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), TWIST)
        except MessageDecodeError as exc:
            log.warning("undecodable cmd_vel for %s: %s", robot, exc)
            return
        v, w = float(msg.linear.x), float(msg.angular.z)
        if not (math.isfinite(v) and math.isfinite(w)):
            log.warning("non-finite cmd_vel for %s ignored", robot)
            return
        with self._lock:
            self._commands[robot] = (v, w, self.t_sim)
            self.commands_received += 1

    def _put(self, key: str, payload: bytes) -> None:
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = self.session.declare_publisher(key)
        pub.put(payload)

    def _wait_for_subscribers(self, stop: threading.Event) -> None:
        keys = [*self.odom_keys.values(), *set(self.range_keys.values())]
        end = time.time() + self.options.wait
        pending = keys
        while pending and time.time() < end and not stop.is_set():
            for k in pending:
                if k not in self._pubs:
                    self._pubs[k] = self.session.declare_publisher(k)
            pending = [k for k in pending if not self._pubs[k].matching_status.matching]
            if pending:
                stop.wait(0.05)
        if pending:
            log.warning("no subscriber yet for %d key(s), publishing anyway", len(pending))

    def run(self, stop: threading.Event | None = None) -> dict[str, Any]:
        """Simulate and publish until ``stop``, ``duration`` or the end of the simulation."""
        stop = stop or threading.Event()
        opts = self.options
        self._wait_for_subscribers(stop)
        end = min(self.sim.duration, opts.duration or math.inf)
        wall0 = time.time()
        self.time_base = wall0 if opts.time_base is None else opts.time_base
        k = 0
        while not stop.is_set():
            k += 1
            t = round(k * opts.step, 9)
            if t > end + 1e-9:
                break
            delay = wall0 + t / opts.rate - time.time()
            if delay > 0:
                stop.wait(delay)
                if stop.is_set():
                    break
            else:
                self.max_behind = max(self.max_behind, -delay)
            self._apply_commands(t - opts.step)
            with self._lock:
                self.t_sim = t
            for ev in self.sim.advance(t):
                self._publish(ev)
        return self.summary()

    def _apply_commands(self, t_now: float) -> None:
        with self._lock:
            commands = dict(self._commands)
        for robot in self.sim.commanded:
            v, w, t_cmd = commands.get(robot, (0.0, 0.0, -math.inf))
            if t_now - t_cmd > self.options.cmd_timeout:
                v, w = 0.0, 0.0
            self.sim.set_command(robot, v, w)

    def _publish(self, ev: Any) -> None:
        base = self.time_base
        if isinstance(ev, OdometryEvent):
            key = self.odom_keys.get(ev.robot)
            if key:
                self._put(key, encode(odometry_msg(replace(ev, t=ev.t + base))))
                self.published += 1
        elif isinstance(ev, RangeEvent):
            key = self.range_keys.get((ev.node_a, ev.node_b))
            if key:
                self._put(key, encode(range_msg(replace(ev, t=ev.t + base))))
                self.published += 1
        elif isinstance(ev, GroundTruthEvent):
            self.truth[ev.robot].append((ev.t + base, ev.x, ev.y, ev.yaw))
            if self.options.ground_truth:
                msg = pose_stamped_msg(ev.t + base, ev.x, ev.y, ev.yaw)
                self._put(self.mocap_keys[ev.robot], encode(msg))
                self.published += 1

    def summary(self) -> dict[str, Any]:
        """Figures of the run, and the true trajectories (stamps on the published clock)."""
        return {
            "simulated_s": round(self.t_sim, 3),
            "time_base": self.time_base,
            "messages": self.published,
            "commands_received": self.commands_received,
            "max_behind_s": round(self.max_behind, 4),
            "reference": self.config.reference,
            "truth": {r: [list(map(float, p)) for p in poses] for r, poses in self.truth.items()},
        }


def save_json(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` as JSON (creating folders)."""
    import json

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))
