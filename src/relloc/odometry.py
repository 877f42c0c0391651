"""Each robot's odometry, put into the team's shared heading frame and queryable at any time.

Robots publish odometry in their own ``odom`` frame, at their own rate, with their own lag. The
filter needs, for any two instants, how far each robot moved in the *shared* heading frame.
``OdometryTrack`` keeps a short history of the robot's pose in that frame and interpolates it
(or extrapolates with the last velocity, for a bounded time) at the instants the filter asks.

Two ways to read a message, chosen per robot in the team config (``odom_mode``):

* ``"pose"``: use the message's pose. Position and yaw are rotated by the robot's heading
  offset (the rotation from its odometry frame to the shared frame: the paper's compass) and
  positions are multiplied by its odometry scale.
* ``"twist"``: integrate the body twist (forward speed along the integrated heading, yaw rate)
  from the first message's pose. Some recordings (the ``/cali/`` topics of the TIERS four-robot bag) freeze the
  orientation of the pose, and their twist integrates to a better path than their positions.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from relloc.events import OdometryEvent


def wrap_angle(a: ArrayLike) -> NDArray[np.float64]:
    """Angles wrapped to ``[-pi, pi)``: the error of 179 deg against -179 deg is 2 deg."""
    return (np.asarray(a, dtype=float) + math.pi) % (2.0 * math.pi) - math.pi


@dataclass
class _Sample:
    t: float
    x: float
    y: float
    yaw: float


MAX_EXTRAPOLATION = 0.5
"""How far past a robot's last odometry message its motion is extrapolated (s): a few missed
messages at 10-30 Hz, not a robot whose odometry has stopped."""


class OdometryTrack:
    """Pose history of one robot in the shared heading frame."""

    def __init__(
        self,
        heading_offset: float = 0.0,
        scale: float = 1.0,
        mode: str = "pose",
        *,
        max_extrapolation: float = MAX_EXTRAPOLATION,
        history: float = 30.0,
    ) -> None:
        if mode not in ("pose", "twist"):
            raise ValueError(f"odometry mode must be 'pose' or 'twist', got {mode!r}")
        self.heading_offset = heading_offset
        self.scale = scale
        self.mode = mode
        self.max_extrapolation = max_extrapolation
        self.history = history
        self._t: list[float] = []
        self._s: list[_Sample] = []
        self._last_event: OdometryEvent | None = None
        self._correction = (0.0, 0.0, 0.0)  # (angle, dx, dy) applied after a re-anchoring
        self._hold_twist = False
        self.reanchors = 0

    @property
    def last_event(self) -> OdometryEvent | None:
        """The last message added, as given (``None`` before the first)."""
        return self._last_event

    def reanchor(self, ev: OdometryEvent) -> None:
        """The next message, ``ev``, jumps (a driver restart, a corrupted integrator): from it
        on, poses are mapped so that ``ev`` continues the track where its last velocity would
        have taken it, instead of moving the robot. Twist mode integrates ``ev`` with the last
        message's velocities instead of its own."""
        self.reanchors += 1
        if self.mode == "twist" or self.empty:
            self._hold_twist = True
            return
        x, y, yaw = self._frame(ev)
        tx, ty, tyaw, _ = self.pose_at(ev.t)
        angle = math.remainder(tyaw - yaw, math.tau)
        c, s = math.cos(angle), math.sin(angle)
        self._correction = (angle, tx - (c * x - s * y), ty - (s * x + c * y))

    def shift_time(self, dt: float) -> None:
        """Every time held moved by ``dt`` (the team's clock stepped)."""
        self._t = [t + dt for t in self._t]
        for sample in self._s:
            sample.t += dt
        if self._last_event is not None:
            self._last_event = replace(self._last_event, t=self._last_event.t + dt)

    def _frame(self, ev: OdometryEvent) -> tuple[float, float, float]:
        """``ev``'s pose in the shared frame, before any re-anchoring."""
        c, s = math.cos(self.heading_offset), math.sin(self.heading_offset)
        return (
            self.scale * (c * ev.x - s * ev.y),
            self.scale * (s * ev.x + c * ev.y),
            ev.yaw + self.heading_offset,
        )

    @property
    def empty(self) -> bool:
        return not self._s

    @property
    def last_time(self) -> float:
        return self._t[-1] if self._t else -math.inf

    def first_after(self, t: float) -> float | None:
        """The stamp of the first message after ``t`` still held (``None``: none)."""
        i = bisect.bisect_right(self._t, t)
        return self._t[i] if i < len(self._t) else None

    def add(self, ev: OdometryEvent) -> None:
        """Append a message; its time must be later than the last one's (the caller checks)."""
        prev = self._last_event
        if self.mode == "pose" or prev is None:
            x, y, yaw = self._frame(ev)
            angle, dx, dy = self._correction
            if angle or dx or dy:
                c, s = math.cos(angle), math.sin(angle)
                x, y, yaw = c * x - s * y + dx, s * x + c * y + dy, yaw + angle
            sample = _Sample(ev.t, x, y, yaw)
        else:
            if self._hold_twist:
                ev = replace(ev, v=prev.v, w=prev.w)
                self._hold_twist = False
            last = self._s[-1]
            dt = ev.t - prev.t
            w = 0.5 * (prev.w + ev.w)
            v = 0.5 * (prev.v + ev.v)
            mid = last.yaw + 0.5 * w * dt
            x = last.x + self.scale * v * dt * math.cos(mid)
            y = last.y + self.scale * v * dt * math.sin(mid)
            sample = _Sample(ev.t, x, y, last.yaw + w * dt)
        self._t.append(ev.t)
        self._s.append(sample)
        self._last_event = ev
        # Forget what the filter can no longer ask for.
        if len(self._t) > 64 and self._t[0] < ev.t - self.history:
            cut = bisect.bisect_left(self._t, ev.t - self.history)
            del self._t[:cut]
            del self._s[:cut]

    def pose_at(self, t: float) -> tuple[float, float, float, float]:
        """``(x, y, yaw, extrapolated_seconds)`` in the shared frame at time ``t``.

        Before the first message the robot is taken to be where the first message puts it;
        after the last, its last velocity is extrapolated for at most ``max_extrapolation``.
        """
        if not self._s:
            raise ValueError("no odometry yet")
        if t <= self._t[0]:
            s = self._s[0]
            return s.x, s.y, s.yaw, 0.0
        if t >= self._t[-1]:
            last = self._s[-1]
            ahead = min(t - self._t[-1], self.max_extrapolation)
            ev = self._last_event
            if ev is None or ahead <= 0.0:
                return last.x, last.y, last.yaw, 0.0
            dx = self.scale * ev.v * ahead
            return (
                last.x + dx * math.cos(last.yaw),
                last.y + dx * math.sin(last.yaw),
                last.yaw + ev.w * ahead,
                ahead,
            )
        i = bisect.bisect_right(self._t, t)
        a, b = self._s[i - 1], self._s[i]
        f = (t - a.t) / (b.t - a.t)
        dyaw = math.remainder(b.yaw - a.yaw, math.tau)
        return a.x + f * (b.x - a.x), a.y + f * (b.y - a.y), a.yaw + f * dyaw, 0.0
