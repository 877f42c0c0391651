"""The navigation loop of one robot: estimate + odometry in, velocity command out.

:class:`Navigator` is what runs at the control rate, in the simulator's closed loop and live
(``relloc navigate``) alike. It is fed events as they arrive and asked for a command at every
control tick:

* :meth:`Navigator.on_estimate` keeps the localizer's latest estimate (positions relative to the
  reference robot, shared heading frame, with covariance);
* :meth:`Navigator.on_odometry` keeps the robot's odometry in an
  :class:`~relloc.odometry.OdometryTrack` configured from the team config (heading offset,
  scale, pose/twist mode), i.e. in the same shared heading frame;
* :meth:`Navigator.update` runs the safety gate, builds the feedback pose and asks the
  :class:`~relloc.navigation.controller.PathFollower` for a command.

Feedback, never ground truth
----------------------------
The position is the estimate's, the heading the odometry's (the paper's compass assumption: the
odometry yaw, rotated by the robot's heading offset, is its heading in the shared frame). The
estimate describes the instant ``estimate.t``, typically 0.1-0.2 s before the control tick (the
localizer fuses measurements in 0.1 s batches and the link adds its delay); moving the
estimated position forward by the robot's own odometry displacement since then
(``latency_compensation``) removes that lag without adding information the robot does not have.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from relloc.config import RobotConfig
from relloc.estimate import Estimate
from relloc.events import OdometryEvent
from relloc.navigation.controller import Command, ControllerConfig, PathFollower
from relloc.navigation.path import WaypointPath
from relloc.navigation.safety import SafetyConfig, SafetyGate
from relloc.odometry import MAX_EXTRAPOLATION, OdometryTrack

__all__ = ["Feedback", "Navigator"]

log = logging.getLogger("relloc.navigation")


@dataclass(frozen=True)
class Feedback:
    """The pose the controller used at one tick (relative frame) and where it came from."""

    t: float
    x: float
    y: float
    yaw: float
    estimate_t: float
    std: float


class Navigator:
    """Safety gate + feedback + path follower for one robot."""

    def __init__(
        self,
        path: WaypointPath,
        robot: RobotConfig,
        *,
        controller: ControllerConfig | None = None,
        safety: SafetyConfig | None = None,
        latency_compensation: bool = True,
        max_odom_extrapolation: float = MAX_EXTRAPOLATION,
    ) -> None:
        self.path = path
        self.robot = robot.name
        self.follower = PathFollower(path, controller)
        self.gate = SafetyGate(safety, robot.name)
        self.latency_compensation = latency_compensation
        self.track = OdometryTrack(
            robot.heading_offset,
            robot.odom_scale,
            robot.odom_mode,
            max_extrapolation=max_odom_extrapolation,
        )
        self.estimate: Estimate | None = None
        self.feedback: Feedback | None = None
        self.last_command: Command = Command.stop("no_estimate")
        self.rejected_odometry = 0
        self.start_time: float | None = None
        """Data time of the first command that let the robot move."""
        self.path_start_time: float | None = None
        """Data time at which the robot reached the first waypoint (the path proper began)."""

    # ---------------------------------------------------------------- inputs
    def on_estimate(self, estimate: Estimate) -> None:
        """Keep ``estimate`` if it is news about this robot (older ones are ignored)."""
        if self.robot not in estimate.positions:
            return
        if self.estimate is not None and estimate.t < self.estimate.t:
            return
        self.estimate = estimate

    def on_odometry(self, event: OdometryEvent) -> None:
        """Add one odometry message of this robot (others, and repeats, are ignored)."""
        if event.robot != self.robot:
            return
        values = (event.t, event.x, event.y, event.yaw, event.v, event.w)
        if not all(map(math.isfinite, values)) or event.t <= self.track.last_time:
            self.rejected_odometry += 1
            return
        self.track.add(event)

    def interrupt(self, now: float, reason: str = "interrupted", detail: str = "") -> Command:
        """Stop for good (Ctrl-C): the returned and every later command is zero."""
        self.gate.stop_for_good(now, reason, detail or "stopped by the operator")
        self.last_command = Command.stop(reason)
        return self.last_command

    # ---------------------------------------------------------------- state
    @property
    def finished(self) -> bool:
        """The path is complete or navigation was interrupted: nothing will move any more."""
        return self.gate.terminal is not None

    @property
    def completed(self) -> bool:
        """The path was driven to its end."""
        return self.follower.done

    @property
    def driving(self) -> bool:
        """The last command let the robot move (it was not held by the gate)."""
        return self.last_command.mode in ("track", "rotate")

    # ---------------------------------------------------------------- control
    def update(self, now: float) -> Command:
        """The command at data time ``now``; zero whenever a safety check fails."""
        odom_t = None if self.track.empty else self.track.last_time
        reason = self.gate.evaluate(now, self.estimate, odom_t)
        if reason is not None:
            self.last_command = Command.stop(reason, "done" if reason == "goal reached" else "stop")
            return self.last_command
        assert self.estimate is not None  # the gate passed
        fb = self._feedback(now, self.estimate)
        self.feedback = fb
        cmd = self.follower.step(fb.x, fb.y, fb.yaw)
        if self.start_time is None:
            self.start_time = now
        if self.path_start_time is None and self.follower.on_path:
            self.path_start_time = now
        if cmd.mode == "done":
            self.gate.stop_for_good(now, "goal reached", f"path {self.path.name!r} complete")
        self.last_command = cmd
        return cmd

    def _feedback(self, now: float, est: Estimate) -> Feedback:
        x, y = est.positions[self.robot]
        ox, oy, yaw, _ = self.track.pose_at(now)
        if self.latency_compensation and now > est.t:
            bx, by, _, _ = self.track.pose_at(est.t)
            x, y = x + (ox - bx), y + (oy - by)
        return Feedback(now, float(x), float(y), float(yaw), est.t, est.std(self.robot))
