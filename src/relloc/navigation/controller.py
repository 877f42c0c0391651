"""A path follower for a differential-drive robot: pure pursuit on the current segment, turning
in place at corners.

The derivation: docs/explanation/internals.md, section ``relloc.navigation.controller``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from relloc.config import ConfigError, with_numeric_overrides
from relloc.navigation.path import FloatArray, WaypointPath

__all__ = ["Command", "ControllerConfig", "PathFollower"]

Mode = Literal["track", "rotate", "done", "stop"]


@dataclass(frozen=True)
class ControllerConfig:
    """Limits and gains of the path follower (defaults suit a TurtleBot 4)."""

    max_v: float = 0.25
    """Forward speed limit (m/s)."""
    max_w: float = 1.0
    """Turn-rate limit (rad/s)."""
    min_v: float = 0.04
    """Speed floor while slowing down towards a corner or the goal (m/s)."""
    lookahead: float = 0.4
    """Distance of the pure-pursuit carrot ahead of the robot's projection (m)."""
    goal_tolerance: float = 0.08
    """The path is complete within this distance of its last point (m)."""
    corner_tolerance: float = 0.03
    """Switch to the next segment within this distance of a corner, along the segment (m)."""
    slowdown_distance: float = 0.4
    """Speed falls linearly to ``min_v`` over this distance before a corner or the goal (m)."""
    rotate_threshold_deg: float = 35.0
    """Turn in place when the carrot is more than this far off the heading."""
    align_tolerance_deg: float = 6.0
    """...until it is within this."""
    k_rotate: float = 1.5
    """Turn rate per radian of heading error while turning in place (1/s)."""
    min_w: float = 0.15
    """Turn-rate floor while turning in place (rad/s): real bases have a dead band."""
    rate_hz: float = 10.0
    """Control rate (Hz): how often a command is computed and sent."""

    def __post_init__(self) -> None:
        positive = ("max_v", "max_w", "lookahead", "goal_tolerance", "corner_tolerance", "rate_hz")
        for name in positive:
            value = getattr(self, name)
            if not isinstance(value, int | float) or not value > 0:
                raise ConfigError(f"controller.{name}: expected a positive number, got {value!r}")
        for name in ("min_v", "min_w", "slowdown_distance", "k_rotate"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not value >= 0:
                raise ConfigError(f"controller.{name}: expected a number >= 0, got {value!r}")
        if not 0 < self.align_tolerance_deg < self.rotate_threshold_deg < 180:
            raise ConfigError(
                "controller: need 0 < align_tolerance_deg < rotate_threshold_deg < 180, got "
                f"{self.align_tolerance_deg} and {self.rotate_threshold_deg}"
            )

    @property
    def period(self) -> float:
        """Control period (s)."""
        return 1.0 / self.rate_hz

    def updated(self, overrides: dict[str, Any], where: str = "controller") -> ControllerConfig:
        """A copy with the keys of ``overrides`` changed (unknown keys are errors)."""
        return with_numeric_overrides(self, overrides, where)


@dataclass(frozen=True)
class Command:
    """A velocity command and why it is what it is.

    ``mode``: ``"track"`` (following a segment), ``"rotate"`` (turning in place), ``"done"``
    (path complete) or ``"stop"`` (held by the safety layer; ``reason`` says why).
    """

    v: float
    w: float
    mode: Mode
    reason: str = ""

    @classmethod
    def stop(cls, reason: str, mode: Mode = "stop") -> Command:
        return cls(0.0, 0.0, mode, reason)

    @property
    def is_zero(self) -> bool:
        return self.v == 0.0 and self.w == 0.0


class PathFollower:
    """Pure pursuit along a waypoint path, segment by segment, turning in place at corners."""

    def __init__(self, path: WaypointPath, config: ControllerConfig | None = None) -> None:
        self.path = path
        self.config = config or ControllerConfig()
        self.reset()

    def reset(self) -> None:
        """Forget progress: the next :meth:`step` starts the path again (with an approach)."""
        self._vertices: FloatArray | None = None
        self._approach = False
        self.segment = 0
        self._rotating = False
        self.done = False
        self.carrot: tuple[float, float] | None = None

    # ---------------------------------------------------------------- state
    @property
    def started(self) -> bool:
        return self._vertices is not None

    @property
    def on_path(self) -> bool:
        """True once the robot has reached the first waypoint (the approach is over)."""
        return self.started and (not self._approach or self.segment >= 1)

    @property
    def vertices(self) -> FloatArray:
        """Polyline being followed: the approach start (if any), then the path's points."""
        if self._vertices is None:
            return self.path.points
        return self._vertices

    @property
    def path_segment(self) -> int:
        """Index of the current segment of the path proper (-1 during the approach)."""
        return self.segment - 1 if self._approach else self.segment

    # ---------------------------------------------------------------- control
    def step(self, x: float, y: float, yaw: float) -> Command:
        """The command for the robot at ``(x, y)`` with heading ``yaw`` (relative frame)."""
        cfg = self.config
        if self.done:
            return Command.stop("goal reached", "done")
        if self._vertices is None:
            pts = self.path.points
            self._approach = math.hypot(x - pts[0, 0], y - pts[0, 1]) > cfg.goal_tolerance
            self._vertices = np.vstack([[x, y], pts]) if self._approach else pts
        verts = self._vertices
        last = len(verts) - 2
        p = np.array([x, y])
        # Advance over every segment whose end is already (nearly) reached.
        while True:
            a, b = verts[self.segment], verts[self.segment + 1]
            seg = b - a
            length = float(np.hypot(*seg))
            u = seg / length
            s = float((p - a) @ u)
            remaining = length - s
            if self.segment == last:
                if remaining < cfg.goal_tolerance and math.hypot(*(p - b)) < 2 * cfg.goal_tolerance:
                    self.done = True
                    self.carrot = (float(b[0]), float(b[1]))
                    return Command.stop("goal reached", "done")
                break
            if remaining < cfg.corner_tolerance:
                self.segment += 1
                continue
            break
        # Carrot on the segment's line (extended past its end); the end itself once overshot.
        carrot = b if remaining < 0.0 else a + u * (max(s, 0.0) + cfg.lookahead)
        self.carrot = (float(carrot[0]), float(carrot[1]))
        dx, dy = carrot - p
        dist = float(math.hypot(dx, dy))
        alpha = math.remainder(math.atan2(dy, dx) - yaw, math.tau)

        threshold = math.radians(cfg.rotate_threshold_deg)
        align = math.radians(cfg.align_tolerance_deg)
        if self._rotating and abs(alpha) < align:
            self._rotating = False
        elif not self._rotating and abs(alpha) > threshold:
            self._rotating = True
        if self._rotating:
            w = float(np.clip(cfg.k_rotate * alpha, -cfg.max_w, cfg.max_w))
            if abs(w) < cfg.min_w:
                w = math.copysign(cfg.min_w, alpha)
            return Command(0.0, w, "rotate")

        # Regulated speed: slow down before a corner or the goal.
        v = cfg.max_v
        if cfg.slowdown_distance > 0:
            v = min(
                v, cfg.min_v + (cfg.max_v - cfg.min_v) * max(remaining, 0.0) / cfg.slowdown_distance
            )
        v = max(v, cfg.min_v) if remaining > 0 else cfg.min_v
        curvature = 2.0 * math.sin(alpha) / max(dist, 1e-6)
        w = v * curvature
        if abs(w) > cfg.max_w:
            w = math.copysign(cfg.max_w, w)
            v = abs(w / curvature)
        return Command(float(v), float(w), "track")
