"""Navigation over Eclipse Zenoh (``relloc navigate``).

The derivation: docs/explanation/internals.md, section ``relloc.navigation.live``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.live.publish import cmd_vel_channel, odom_channel
from relloc.navigation.controller import Command, ControllerConfig
from relloc.navigation.navigator import Navigator
from relloc.navigation.path import WaypointPath
from relloc.navigation.safety import SafetyConfig
from relloc.ros.interfaces import RosInterface
from relloc.ros.messages import (
    ODOMETRY,
    POSE_WITH_COVARIANCE_STAMPED,
    MessageDecodeError,
    decode,
    encode,
    odometry_to_event,
    stamp_to_sec,
    twist_msg,
)
from relloc.ros.zenoh_node import ZenohNode

__all__ = [
    "DataClock",
    "LiveNavigation",
    "NavigateOptions",
    "NavigationLoop",
    "decode_estimate",
]

log = logging.getLogger("relloc.navigation")


# ============================================================================ messages
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
    interface: RosInterface = field(default_factory=RosInterface)
    """How the robots and the server are on Zenoh: ``bridge`` or ``rmw_zenoh``."""
    estimate_prefix: str = "relloc"
    """Key prefix of the estimates (``relloc serve --out-prefix``)."""
    clock_rate: float = 1.0
    in_process: bool = False
    """Run the localizer in this process instead of subscribing to ``relloc serve``."""
    methods: tuple[str, ...] = ("pf",)
    seed: int = 0
    particles: int | None = None
    reorder_window: float = 0.1
    """With ``in_process``: the server's reorder window (s of header time). Events fused in
    header order, not arrival order, give the same estimates on every run of the same data;
    the latency it adds is removed by ``latency_compensation``."""
    latency_compensation: bool = True
    duration: float | None = None
    pose_identity: str | None = None
    """The certificate common name the estimates must come from (``--secure``): a pose is used
    only while a link authenticated as it is up; otherwise the robot is held (``unverified``)."""


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
        )
        self.clock = DataClock(opts.clock_rate)
        from relloc.sinks.zenoh_sink import pose_topic

        iface = opts.interface
        self.cmd_channel = cmd_vel_channel(robot, iface, opts.prefix)
        self.odom_channel = odom_channel(robot, iface, opts.prefix)
        self.pose_channel = iface.channel(
            pose_topic(opts.estimate_prefix, robot.name), POSE_WITH_COVARIANCE_STAMPED
        )
        self.cmd_key = self.cmd_channel.key
        self.odom_key = self.odom_channel.key
        self.pose_key = self.pose_channel.key
        self.node = ZenohNode(session, iface, "relloc_navigate")
        self._cmd_pub = self.node.publisher(self.cmd_channel)
        self.loop = NavigationLoop(
            self.navigator, self._publish, self.clock.now, clock_rate=opts.clock_rate
        )
        self.received = {"odometry": 0, "estimate": 0, "decode_error": 0, "unverified": 0}
        self.t0: float | None = None
        """Stamp of the first odometry message (the printed times are relative to it)."""
        self.server: Any = None
        self._server_thread: threading.Thread | None = None

    # ---------------------------------------------------------------- zenoh side
    def start(self) -> None:
        """Declare subscribers (and start the in-process server)."""
        self.node.subscribe(self.odom_channel, self._on_odom)
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
                    interface=opts.interface,
                    out_prefix=opts.estimate_prefix,
                    reorder_window=opts.reorder_window,
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
            self.node.subscribe(self.pose_channel, self._on_pose)

    def close(self) -> None:
        """Stop the in-process server, undeclare everything (the session stays open)."""
        if self.server is not None:
            self.server.stop()
            if self._server_thread is not None:
                self._server_thread.join(timeout=10)
            self.server.close()
        self.node.close()

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

    def _why_unverified(self) -> str | None:
        """Why the pose that just came cannot be told to be from ``pose_identity`` (``None``
        if it can). The access control lets only links authenticated as it deliver poses, so a
        link of that identity must be up; Zenoh does not say which link a sample came on."""
        identity = self.options.pose_identity
        if identity is None:
            return None
        try:
            linked = any(link.auth_identifier == identity for link in self.session.info.links())
        except Exception as exc:  # a closing session
            return f"cannot list the session's links: {exc}"
        return None if linked else f"no link authenticated as {identity!r}"

    def _on_pose(self, sample: Any) -> None:
        why = self._why_unverified()
        if why is not None:
            with self.loop.lock:
                self.navigator.gate.untrusted = why
            self.received["unverified"] += 1
            log.warning("estimate on %s not used: %s", self.pose_key, why)
            return
        try:
            est = decode_estimate(sample.payload.to_bytes(), self.robot.name, self.config.reference)
        except MessageDecodeError as exc:
            self.received["decode_error"] += 1
            log.warning("undecodable estimate on %s: %s", self.pose_key, exc)
            return
        with self.loop.lock:
            self.navigator.gate.untrusted = None
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
