"""A team's range points: one per robot, or one per tag of a robot with several.

A robot with two or more UWB tags (``[[robots]] tags``) is a rigid body whose heading its ranges
see: the smoother and multilateration give each of its tags a point of its own, tied to its
siblings by a tight range at their lever arms' distance (:data:`RIGID_SIGMA`), so their problem
stays one of points. A robot's pose is the rigid fit of its lever arms to its points (the 2D
Procrustes rotation), its heading that fit's angle. Published positions are robot positions;
where the reference has several tags they are in its body frame, and each multi-tag robot's
heading relative to the reference's is published too. Their covariance is the joint marginal of
the points pushed through the Jacobian of that map (central differences: a handful of points).
Ranges never tell the formation from its mirror image: the caller decides whether the
orientation is observed (docs/explanation/tags.md).

A team with one tag per robot has exactly its robots as points (``identity``), and nothing of
this module changes its estimates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.filter.factors import RangeTerms
from relloc.filter.state import TeamLayout

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

RIGID_SIGMA = 0.01
"""Std (m) of the range that ties two tags of one robot at their lever arms' distance."""


@dataclass(frozen=True)
class TagPoints:
    """The points of a team (module docstring), in team order, a robot's tags together."""

    robot: IntArray
    """``(P,)``: the robot of each point."""
    arm: FloatArray
    """``(P, 2)``: each point's lever arm in its robot's body frame (0 for a one-point robot)."""
    first: IntArray
    """``(N,)``: each robot's first point."""
    of_node: dict[str, int]
    """Node id -> its point."""
    reference: int
    """The reference robot's team index."""

    @classmethod
    def of(cls, config: TeamConfig, layout: TeamLayout) -> TagPoints:
        robot: list[int] = []
        arm: list[tuple[float, float]] = []
        first: list[int] = []
        of_node: dict[str, int] = {}
        for i, name in enumerate(layout.robots):
            tags = config.robot(name).tag_list
            first.append(len(robot))
            if len(tags) >= 2:
                for tag in tags:
                    of_node[tag.node] = len(robot)
                    robot.append(i)
                    arm.append((tag.lever_arm[0], tag.lever_arm[1]))
            else:
                for tag in tags:
                    of_node[tag.node] = len(robot)
                robot.append(i)
                arm.append((0.0, 0.0))
        return cls(
            np.array(robot, np.intp),
            np.array(arm, float).reshape(-1, 2),
            np.array(first, np.intp),
            of_node,
            layout.index(layout.reference),
        )

    @property
    def size(self) -> int:
        return int(self.robot.size)

    @property
    def identity(self) -> bool:
        """One point per robot: the robots themselves."""
        return self.size == self.first.size

    @property
    def reference_point(self) -> int:
        return int(self.first[self.reference])

    @cached_property
    def _several(self) -> NDArray[np.bool_]:
        """``(N,)``: each robot's having several points (tags)."""
        return np.bincount(self.robot, minlength=self.first.size) >= 2

    def multi(self, robot: int) -> bool:
        """Whether ``robot`` has several points (tags)."""
        return bool(self._several[robot])

    @property
    def oriented(self) -> bool:
        """Whether the reference has several tags: its heading, and the formation's
        orientation in its body frame, are observed."""
        return self.multi(self.reference)

    def point(self, robot: int, node: str) -> int:
        """The point a range of ``robot``'s node ``node`` reaches."""
        return self.of_node.get(node, int(self.first[robot]))

    def points_of(self, robots: IntArray, nodes: tuple[tuple[str, str], ...], end: int) -> IntArray:
        """The points ranges of ``robots`` reach: their tags ``nodes[k][end]`` (a
        :class:`~relloc.filter.ranges.RangeBatch`'s ``nodes``, ``end`` 0 for ``index_a``)."""
        if self.identity:
            return robots
        pairs = nodes or (("", ""),) * robots.size
        return np.array(
            [self.point(r, pair[end]) for r, pair in zip(robots.tolist(), pairs, strict=True)],
            dtype=np.intp,
        )

    def with_rigid(self, terms: RangeTerms) -> RangeTerms:
        """``terms`` (point indices) and the ranges that hold each robot's tags at their lever
        arms' distance."""
        a, b, d = self.rigid
        if not a.size:
            return terms
        return RangeTerms(
            np.concatenate([terms.index_a, a]),
            np.concatenate([terms.index_b, b]),
            np.concatenate([terms.distance, d]),
            np.concatenate([terms.sigma, np.full(a.size, RIGID_SIGMA)]),
            np.concatenate([terms.bias, np.full(a.size, -1, np.intp)]),
        )

    @cached_property
    def rigid(self) -> tuple[IntArray, IntArray, FloatArray]:
        """Every two points of one robot and the distance of their lever arms (computed once:
        every step of the smoother and of multilateration adds them)."""
        a, b, d = [], [], []
        for i in range(self.size):
            for j in range(i + 1, self.size):
                if self.robot[i] == self.robot[j]:
                    a.append(i)
                    b.append(j)
                    d.append(float(np.hypot(*(self.arm[i] - self.arm[j]))))
        return np.array(a, np.intp), np.array(b, np.intp), np.array(d, float)

    def poses(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Each robot's position ``(N, 2)`` and heading ``(N,)`` (NaN for a one-point robot)
        from its points ``(P, 2)`` (module docstring)."""
        n = self.first.size
        pos = np.empty((n, 2))
        yaw = np.full(n, math.nan)
        for r in range(n):
            idx = np.flatnonzero(self.robot == r)
            if idx.size < 2:
                pos[r] = points[idx[0]]
                continue
            w, arm = points[idx], self.arm[idx]
            cw, ca = w.mean(axis=0), arm.mean(axis=0)
            dw, da = w - cw, arm - ca
            cross = float(np.sum(da[:, 0] * dw[:, 1] - da[:, 1] * dw[:, 0]))
            dot = float(np.sum(da[:, 0] * dw[:, 0] + da[:, 1] * dw[:, 1]))
            th = math.atan2(cross, dot)
            c, s = math.cos(th), math.sin(th)
            pos[r] = cw - np.array([c * ca[0] - s * ca[1], s * ca[0] + c * ca[1]])
            yaw[r] = th
        return pos, yaw

    def published(self, points: FloatArray, body: bool = True) -> FloatArray:
        """The published vector of the points ``(P, 2)``: each non-reference robot's position
        relative to the reference (in its body frame where :attr:`oriented` and ``body``), then
        each multi-tag non-reference robot's heading (relative to the reference's there).
        ``body`` False: in the points' own frame (the orientation is a gauge: a frame that
        follows the reference's short baseline would jitter with it)."""
        pos, yaw = self.poses(points)
        ref = self.reference
        rel = pos - pos[ref]
        turn = 0.0
        if self.oriented and body:
            turn = -float(yaw[ref])
            c, s = math.cos(turn), math.sin(turn)
            rel = rel @ np.array([[c, s], [-s, c]])
        others = [r for r in range(self.first.size) if r != ref]
        headings = [math.remainder(float(yaw[r]) + turn, math.tau) for r in others if self.multi(r)]
        return np.concatenate([rel[others].reshape(-1), np.array(headings, float)])

    def moments(
        self, points: FloatArray, joint: FloatArray, body: bool = True
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Positions ``(N-1, 2)`` and covariances ``(N-1, 2, 2)`` of the non-reference robots
        and the headings ``(H,)`` and their stds ``(H,)`` of the multi-tag ones
        (:meth:`published`), from the points ``(P, 2)`` and their joint covariance
        ``(2P, 2P)``, in the frame :meth:`published` says for ``body`` (module docstring)."""
        f0 = self.published(points, body)
        flat = points.reshape(-1)
        jac = np.empty((f0.size, flat.size))
        eps = 1e-6
        for k in range(flat.size):
            up, down = flat.copy(), flat.copy()
            up[k] += eps
            down[k] -= eps
            diff = self.published(up.reshape(-1, 2), body) - self.published(
                down.reshape(-1, 2), body
            )
            k_heads = slice(2 * (self.first.size - 1), None)
            diff[k_heads] = np.remainder(diff[k_heads] + math.pi, math.tau) - math.pi
            jac[:, k] = diff / (2.0 * eps)
        cov = jac @ joint @ jac.T
        k = self.first.size - 1
        mean = f0[: 2 * k].reshape(k, 2)
        blocks = np.stack([cov[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] for i in range(k)])
        head_var = np.diag(cov)[2 * k :]
        return mean, 0.5 * (blocks + blocks.transpose(0, 2, 1)), f0[2 * k :], np.sqrt(head_var)

    def heading_robots(self) -> list[int]:
        """The non-reference robots whose heading :meth:`published` gives, in its order."""
        return [r for r in range(self.first.size) if r != self.reference and self.multi(r)]
