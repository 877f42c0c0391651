"""Exact kinematics of the simulated world: static objects, robot motions, trajectories.

Motion is a sequence of constant-twist segments (straight lines, turns in place, circular
arcs) integrated in closed form (:class:`Trajectory`), so ground truth has no integration error
and the odometry error is exactly the error model's, nothing else. The pattern builders
(:func:`polygon_loop`, :func:`circle_loop`, :func:`looped_motion`) turn the paper's patterns into
such segments.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from relloc.odometry import wrap_angle
from relloc.simulator.streams import stream

FloatArray = NDArray[np.float64]

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class SimObject:
    """A static object in the world."""

    label: str
    x: float
    y: float
    z: float = 0.5
    """Height of the object's centre above the floor (m)."""


@dataclass(frozen=True)
class RobotMotion:
    """How one simulated robot moves.

    The robot starts at ``(x, y, yaw)`` (world frame) and executes ``segments``, a sequence
    of ``(duration, v, w)`` constant-twist pieces, then stands still; a ``commanded`` robot
    ignores ``segments`` and executes :meth:`Simulation.set_command` instead.
    """

    name: str
    node: str
    x: float
    y: float
    yaw: float
    segments: tuple[tuple[float, float, float], ...] = ()
    commanded: bool = False
    pattern: str = ""
    """Name of the pattern, for display only."""
    tags: tuple[tuple[str, tuple[float, float]], ...] = ()
    """The robot's UWB tags, ``(node, lever arm in the body frame)``; empty: one, ``node`` at
    the body origin."""

    @property
    def tag_list(self) -> tuple[tuple[str, tuple[float, float]], ...]:
        """The robot's tags: ``tags``, or ``node`` at the body origin."""
        return self.tags or ((self.node, (0.0, 0.0)),)


class Trajectory:
    """Piecewise constant-twist motion of a unicycle, integrated in closed form.

    Segment ``k`` starts at ``t0[k]`` in state ``(x, y, yaw, s)`` (yaw unwrapped, ``s`` the
    signed path length) and moves with ``(v[k], w[k])``; the last entry is the end state, at
    rest forever after. Evaluation is vectorised over time.
    """

    def __init__(self, x: float, y: float, yaw: float) -> None:
        self._t0 = np.zeros(1)
        self._state = np.array([[x, y, yaw, 0.0]])
        self._v = np.zeros(1)
        self._w = np.zeros(1)

    @property
    def end_time(self) -> float:
        return float(self._t0[-1])

    def copy(self) -> Trajectory:
        new = Trajectory.__new__(Trajectory)
        new._t0, new._state, new._v, new._w = self._t0, self._state, self._v, self._w
        return new  # arrays are never modified in place, so sharing them is safe

    def extend(self, durations: ArrayLike, v: ArrayLike, w: ArrayLike) -> None:
        """Append segments after the current end."""
        d = np.asarray(durations, dtype=float)
        if d.size == 0:
            return
        v = np.broadcast_to(np.asarray(v, dtype=float), d.shape)
        w = np.broadcast_to(np.asarray(w, dtype=float), d.shape)
        x, y, yaw, s = self._state[-1]
        yaw_end = accumulate(yaw, w * d)
        yaw_start = yaw_end - w * d
        dx, dy = arc_displacement(yaw_start, v, w, d)
        states = np.column_stack(
            [accumulate(x, dx), accumulate(y, dy), yaw_end, accumulate(s, v * d)]
        )
        self._t0 = np.concatenate([self._t0, self._t0[-1] + np.cumsum(d)])
        self._state = np.concatenate([self._state, states])
        self._v = np.concatenate([self._v[:-1], v, [0.0]])
        self._w = np.concatenate([self._w[:-1], w, [0.0]])

    def evaluate(self, t: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """``x, y, yaw (unwrapped), s`` at times ``t`` (before 0: the start; after the end: the
        end state)."""
        t = np.asarray(t, dtype=float)
        k = np.clip(np.searchsorted(self._t0, t, side="right") - 1, 0, None)
        tau = np.maximum(t - self._t0[k], 0.0)
        x0, y0, yaw0, s0 = self._state[k].T
        v, w = self._v[k], self._w[k]
        dx, dy = arc_displacement(yaw0, v, w, tau)
        return x0 + dx, y0 + dy, yaw0 + w * tau, s0 + v * tau


def arc_displacement(
    yaw: FloatArray, v: FloatArray, w: FloatArray, dt: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """World displacement of a unicycle moving with constant ``(v, w)`` for ``dt`` from ``yaw``.

    The chord of the arc, ``v dt sin(w dt / 2) / (w dt / 2)``, along the mean heading: exact
    for any ``w`` including 0 (``np.sinc`` handles the limit).
    """
    chord = v * dt * np.sinc(w * dt / TWO_PI)
    mid = yaw + 0.5 * w * dt
    return chord * np.cos(mid), chord * np.sin(mid)


def accumulate(start: float, steps: FloatArray) -> FloatArray:
    """``start + steps[0]``, ``start + steps[0] + steps[1]``, ... summed strictly in order.

    Unlike ``start + np.cumsum(steps)``, continuing from the last value later gives bit-for-bit
    the same numbers as one long sum, so a run cut into steps equals the run in one go.
    """
    return np.cumsum(np.concatenate(([start], steps)))[1:]


def polygon_loop(
    vertices: Sequence[tuple[float, float]], speed: float, turn_rate: float
) -> tuple[tuple[float, float, float], list[tuple[float, float, float]]]:
    """One loop of a closed polygon: drive each edge straight, turn in place at each corner.

    Returns the start pose (first vertex, heading along the first edge) and the segments.
    """
    P = np.asarray(vertices, dtype=float)
    n = len(P)
    edges = np.roll(P, -1, axis=0) - P
    headings = np.arctan2(edges[:, 1], edges[:, 0])
    segments: list[tuple[float, float, float]] = []
    for i in range(n):
        segments.append((float(np.hypot(*edges[i])) / speed, speed, 0.0))
        turn = float(wrap_angle(headings[(i + 1) % n] - headings[i]))
        if abs(turn) > 1e-9:
            segments.append((abs(turn) / turn_rate, 0.0, math.copysign(turn_rate, turn)))
    return (float(P[0, 0]), float(P[0, 1]), float(headings[0])), segments


def circle_loop(
    cx: float, cy: float, radius: float, speed: float, start_angle: float = -math.pi / 2
) -> tuple[tuple[float, float, float], list[tuple[float, float, float]]]:
    """One counter-clockwise circle; starts at ``start_angle`` on it, heading along it."""
    x = cx + radius * math.cos(start_angle)
    y = cy + radius * math.sin(start_angle)
    return (x, y, start_angle + math.pi / 2), [(TWO_PI * radius / speed, speed, speed / radius)]


def looped_motion(
    name: str,
    node: str,
    pattern: str,
    loop: tuple[tuple[float, float, float], list[tuple[float, float, float]]],
    *,
    seed: int,
    duration: float,
    initial_yaw: float | None,
    turn_rate: float,
    commanded: bool,
) -> RobotMotion:
    """Repeat a loop for the whole run, starting at a random point of it (seeded phase).

    With ``initial_yaw``, the robot starts with that heading and first turns in place onto
    the pattern; with ``None`` it starts heading along the pattern.
    """
    start, seg = loop
    period = sum(s[0] for s in seg)
    phase = float(stream(seed, "phase", name).uniform(0.0, period))
    n_loops = math.ceil((phase + duration) / period) + 1
    full = np.asarray(seg * n_loops, dtype=float)
    traj = Trajectory(*start)
    traj.extend(full[:, 0], full[:, 1], full[:, 2])
    x, y, yaw, _ = (float(a[0]) for a in traj.evaluate(np.array([phase])))
    # Cut the segment list at the phase.
    ends = np.cumsum(full[:, 0])
    k = int(np.searchsorted(ends, phase, side="right"))
    first = (float(ends[k] - phase), float(full[k, 1]), float(full[k, 2]))
    segments = [first, *(tuple(map(float, r)) for r in full[k + 1 :])]
    if initial_yaw is not None:
        turn = float(wrap_angle(yaw - initial_yaw))
        if abs(turn) > 1e-9:
            segments.insert(0, (abs(turn) / turn_rate, 0.0, math.copysign(turn_rate, turn)))
        yaw = initial_yaw
    return RobotMotion(
        name=name,
        node=node,
        x=x,
        y=y,
        yaw=float(wrap_angle(yaw)),
        segments=tuple(segments),  # type: ignore[arg-type]
        commanded=commanded,
        pattern=pattern,
    )
