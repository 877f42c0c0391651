"""Every robot's odometry track, guarded against resets and jumps.

Each robot's odometry goes into an :class:`~relloc.odometry.OdometryTrack` (in the frame the
localizer asks for: the shared heading frame, or the robot's own where the filter estimates
the heading), so that the localizer can predict to any instant. A message that moves its robot
faster than ``MAX_SPEED`` / ``MAX_YAW_RATE`` is a reset or a step of
the integrator: it re-anchors the track instead of moving the robot (counted per robot in
:attr:`OdometryTracks.faults`). The tracks also keep each robot's first sample and a bounded
log of odometry yaws at estimate times (for evaluating headings; the filter does not use it).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable

from relloc.config import TeamConfig
from relloc.events import OdometryEvent
from relloc.odometry import OdometryTrack

log = logging.getLogger(__name__)

_TIME_TOLERANCE = 1e-9
MAX_SPEED = 1.5
"""Fastest a robot's odometry may move it (m/s; ground robots): a faster step between two
messages (beyond ``_SPEED_SLACK``) is a reset or a jump."""
MAX_YAW_RATE = 4.0
"""Fastest a robot's odometry may turn it (rad/s; beyond ``_YAW_SLACK``), as ``MAX_SPEED``."""
_SPEED_SLACK = 0.25
"""Odometry displacement (m) allowed beyond ``MAX_SPEED * dt`` (jitter over short intervals)."""
_YAW_SLACK = 0.3
"""Odometry turn (rad) allowed beyond ``MAX_YAW_RATE * dt``."""
_YAW_LOG = 200_000
"""Odometry yaws kept per robot for evaluating estimated headings: 5.5 h at 10 Hz."""


class OdometryTracks:
    """The team's odometry tracks (module docstring)."""

    def __init__(self, config: TeamConfig, frame: Callable[[str], tuple[float, float]]) -> None:
        """``frame(robot)``: the heading offset and odometry scale that robot's track applies."""
        self.tracks = {r.name: OdometryTrack(*frame(r.name), r.odom_mode) for r in config.robots}
        self.first: dict[str, tuple[float, float]] = {}
        """Per robot, ``(t, yaw)`` of its first odometry sample (in its track's frame)."""
        self.yaws: dict[str, deque[tuple[float, float]]] = {}
        """Robots' odometry yaws at estimate times (:meth:`log_yaw`), bounded for live runs."""
        self.faults: dict[str, int] = {}
        """Per robot, how many odometry resets or jumps re-anchored its track."""

    def stale(self, event: OdometryEvent) -> bool:
        """Whether ``event`` is not after its robot's newest odometry (out of order, a repeat)."""
        return event.t <= self.tracks[event.robot].last_time + _TIME_TOLERANCE

    def add(self, event: OdometryEvent) -> bool:
        """Add ``event`` to its robot's track; True if it re-anchored the track (a jump)."""
        track = self.tracks[event.robot]
        jumped = not track.empty and self._implausible(track, event)
        if jumped:
            track.reanchor(event)
            self.faults[event.robot] = self.faults.get(event.robot, 0) + 1
            log.warning(
                "odometry of %s jumped at t=%.3f (reset or step): track re-anchored",
                event.robot,
                event.t,
            )
        first = track.empty
        track.add(event)
        if first:
            self.first[event.robot] = (event.t, track.pose_at(event.t)[2])
        return jumped

    def _implausible(self, track: OdometryTrack, event: OdometryEvent) -> bool:
        """Whether ``event`` moves its robot faster than a ground robot can (a reset, a step
        of the integrator), with a slack for jitter over short intervals."""
        last = track.last_event
        if last is None:
            return False
        dt = max(event.t - last.t, 0.0)
        if track.mode == "twist":
            return abs(event.v) > MAX_SPEED or abs(event.w) > MAX_YAW_RATE
        dist = math.hypot(event.x - last.x, event.y - last.y) * track.scale
        turn = abs(math.remainder(event.yaw - last.yaw, math.tau))
        return dist > MAX_SPEED * dt + _SPEED_SLACK or turn > MAX_YAW_RATE * dt + _YAW_SLACK

    def pose(self, robot: str, t: float) -> tuple[float, float, float]:
        """``robot``'s odometry pose ``(x, y, yaw)`` at ``t`` (NaN before its first sample)."""
        track = self.tracks[robot]
        if track.empty:
            return (math.nan, math.nan, math.nan)
        x, y, yaw, _ = track.pose_at(t)
        return (x, y, yaw)

    def log_yaw(self, robot: str, t: float) -> None:
        """Keep ``robot``'s odometry yaw at ``t`` (none before its first sample)."""
        track = self.tracks[robot]
        if not track.empty:
            self.yaws.setdefault(robot, deque(maxlen=_YAW_LOG)).append((t, track.pose_at(t)[2]))

    def follow(self, dt: float) -> None:
        """The team's clock stepped by ``dt``. Back in time, the tracks' history moves with it
        (new odometry must come after it); forward, it stays: the first odometry after the
        step then spans it, and a real gap in a recording keeps the motion made meanwhile."""
        if dt < 0:
            for track in self.tracks.values():
                track.shift_time(dt)
