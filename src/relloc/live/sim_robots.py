"""Simulated robots on Eclipse Zenoh (``relloc sim-robots``): a team that stands in for real ones.

:class:`SimRobots` runs a simulated team (:mod:`relloc.simulator`) in real time (times
``rate``) and publishes its odometry, UWB ranges, heights (flying robots' range finders) and
motion capture as real robots behind zenoh-bridge-ros2dds, or running rmw_zenoh, would: the
same keys, attachments (and liveliness tokens, for a node ``relloc_sim_robots``) and ROS 2 CDR
payloads, encoded by the :class:`~relloc.live.publish.EventEncoder` that also publishes
recorded and simulated events for ``relloc replay`` and the benchmarks. Commanded robots obey
``geometry_msgs/Twist`` on their ``cmd_vel`` key, and stop when no command has come for
``cmd_timeout`` simulated seconds, as a robot base does. With it, ``relloc serve`` and
``relloc navigate`` run the whole live system on one machine.

The simulation advances in fixed steps of simulated time, each published no earlier than its
wall-clock schedule (``step / rate``); commands received during a step apply from the next.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any

from relloc.config import TeamConfig
from relloc.events import GroundTruthEvent
from relloc.live.publish import EventEncoder, Publishers, cmd_vel_channel
from relloc.ros.interfaces import RosInterface
from relloc.ros.messages import TWIST, MessageDecodeError, decode

__all__ = ["SimRobots", "SimRobotsOptions", "sim_team_config"]

log = logging.getLogger(__name__)


def sim_team_config(
    sim: Any, base: TeamConfig | None = None, particles: int | None = None
) -> TeamConfig:
    """The team config for a simulated team published over Zenoh.

    The simulator's own config (truthful calibration) with ROS topics: odometry on
    ``/<robot>/odom``, velocity commands on ``/<robot>/cmd_vel``, motion capture body = robot
    name, heights on the simulator's height topics (robots it simulates a range finder for, at
    their body origin). With ``base`` (a user's config for the same robot names) its topics,
    scopes and filter settings are used instead.
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
            config,
            filter=base.filter,
            uwb=replace(config.uwb, range_topic=base.uwb.range_topic),
            ros_interface=base.ros_interface,
            ros_distro=base.ros_distro,
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
            height_topic=(
                own.height_topic if own and own.height_topic and r.height_topic else r.height_topic
            ),
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
    interface: RosInterface = field(default_factory=RosInterface)
    """Stand in for robots behind a bridge (``bridge``) or running ``rmw_zenoh``."""
    cmd_timeout: float = 0.5
    """A commanded robot stops when no ``cmd_vel`` arrived for this long (simulated s)."""
    ground_truth: bool = True
    """Publish the true poses as motion capture (``mocap_topic``) for evaluation."""
    wait: float = 10.0
    """Wait up to this long (wall s) for a subscriber of the odometry and range keys."""
    time_base: float | None = None
    """Added to every stamp (default: the next whole second of wall time, when the run starts;
    stamps look like ROS time). A whole second keeps the stamps' phase on the localizer's batch
    grid the same from run to run, and with it the estimates (see :meth:`SimRobots.run`)."""
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
        self.encoder = EventEncoder(
            config, interface=opts.interface, prefix=opts.prefix, ground_truth=opts.ground_truth
        )
        self.odom_keys = self.encoder.odom_keys
        self.range_keys = self.encoder.range_keys
        self.cmd_channels = {
            name: cmd_vel_channel(config.robot(name), opts.interface, opts.prefix)
            for name in sim.commanded
        }
        self.cmd_keys = {name: c.key for name, c in self.cmd_channels.items()}
        self._pubs = Publishers(session, opts.interface, "relloc_sim_robots")
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
        """Subscribe to the commanded robots' ``cmd_vel`` topics."""
        for robot, channel in self.cmd_channels.items():

            def on_cmd(sample: Any, robot: str = robot) -> None:
                self._on_cmd(robot, sample)

            self._pubs.node.subscribe(channel, on_cmd)

    def close(self) -> None:
        """Undeclare subscribers, publishers and tokens."""
        self._pubs.close()

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

    def run(self, stop: threading.Event | None = None) -> dict[str, Any]:
        """Simulate and publish until ``stop``, ``duration`` or the end of the simulation."""
        stop = stop or threading.Event()
        opts = self.options
        if self._pubs.wait_matching(self.encoder.channels, opts.wait, stop.is_set):
            log.warning("no subscriber yet for some of the team's keys, publishing anyway")
        end = min(self.sim.duration, opts.duration or math.inf)
        wall0 = time.time()
        if opts.time_base is None:
            # Start on a whole second: the localizer batches on a grid of absolute stamps, so a
            # time base with a run-dependent fraction would batch the same data differently
            # each run and give other estimates (a different run, as with another seed).
            wall0 = float(math.ceil(wall0))
            if stop.wait(max(wall0 - time.time(), 0.0)):
                return self.summary()
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
        if isinstance(ev, GroundTruthEvent):
            x, y = ev.position[0], ev.position[1]
            self.truth[ev.robot].append((ev.t + self.time_base, x, y, ev.yaw))
        out = self.encoder.encode(ev, self.time_base)
        if out is not None:
            self._pubs.put(*out)
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
