"""The 3D smoother's start: level poses from the start window's ranges and heights.

Each tag is a point at its robot's height plus its lever arm's z (the start window's median
height; 0 for a robot without one). A range's horizontal part ``sqrt(d^2 - dz^2)`` between
two tags, with each robot's own tags held at their arms' horizontal distance, is a planar
range graph: its shape (:func:`relloc.filter.range_shape.shape_from_ranges`) places every
tag. A robot's yaw and position are the rigid fit of its arms onto its tags (one tag: the
yaw is unknown, 0 with a wide std). Put in the reference's frame, that is one hypothesis; the
mirror image of the shape is the other (ranges never tell them apart; motion does), and where
the reference has a single tag its yaw is unknown too: ``ROTATIONS`` turns of each.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from relloc.filter.range_shape import shape_from_ranges

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

ROTATIONS = 8
"""Yaw hypotheses per handedness where the reference has one tag."""
POSITION_SIGMA = 0.3
"""Smallest std (m per axis) of a started robot's position."""
YAW_SIGMA = 0.3
"""Std (rad) of a started yaw its tags fix."""
UNKNOWN_YAW_SIGMA = math.pi
"""Std (rad) of a yaw nothing at the start fixes."""
WIDE_SIGMA = 10.0
"""Std (m) of a robot no range places."""


def level_start(
    tag_robot: IntArray,
    arms: FloatArray,
    heights: FloatArray,
    ranges: tuple[IntArray, IntArray, FloatArray],
    reference: int,
) -> tuple[FloatArray, FloatArray, float] | None:
    """Hypotheses ``(M, N, 4)`` of every robot's ``(x, y, z, yaw)`` relative to the
    reference's position and yaw, their stds ``(M, N, 4)`` and the shape's RMS residual, from
    the tags' robots ``tag_robot`` ``(P,)``, lever arms ``(P, 3)``, the robots' heights
    ``(N,)`` and the tag ranges ``(tag_a, tag_b, distance)``; ``None`` where no range places
    the reference's tags."""
    n = heights.size
    p = tag_robot.size
    ta, tb, d = ranges
    tag_z = heights[tag_robot] + arms[:, 2]
    dz = tag_z[ta] - tag_z[tb]
    flat = np.sqrt(np.maximum(d * d - dz * dz, 1e-4))
    same = [(i, j) for i in range(p) for j in range(i + 1, p) if tag_robot[i] == tag_robot[j]]
    ia = np.concatenate([ta, np.array([i for i, _ in same], np.intp)])
    ib = np.concatenate([tb, np.array([j for _, j in same], np.intp)])
    rigid = [float(np.hypot(*(arms[i, :2] - arms[j, :2]))) for i, j in same]
    dist = np.concatenate([flat, np.array(rigid)])
    ref_tags = np.flatnonzero(tag_robot == reference)
    shape = shape_from_ranges(p, int(ref_tags[0]), ia, ib, dist)
    if shape.measured == 0 or not shape.placed[ta].any():
        return None
    turns = 1 if ref_tags.size >= 2 else ROTATIONS
    hypotheses, stds = [], []
    for mirror in (1.0, -1.0):
        points = shape.relative * np.array([1.0, mirror])
        poses, sigma = _fit(points, shape.placed, tag_robot, arms, n)
        poses[:, 2] = heights
        ref = poses[reference].copy()
        for k in range(turns):
            turn = 2.0 * math.pi * k / turns
            hypotheses.append(_in_frame(poses, ref, turn))
            stds.append(sigma)
    position = max(POSITION_SIGMA, 2.0 * shape.rms)
    out_sigma = np.array(stds)
    out_sigma[..., :3] = np.maximum(out_sigma[..., :3], position)
    if turns > 1:
        out_sigma[..., 3] = UNKNOWN_YAW_SIGMA
    return np.array(hypotheses), out_sigma, float(shape.rms)


def _fit(
    points: FloatArray, placed: NDArray[np.bool_], tag_robot: IntArray, arms: FloatArray, n: int
) -> tuple[FloatArray, FloatArray]:
    """Each robot's ``(x, y, 0, yaw)`` from its tags' planar ``points`` (the rigid fit of its
    arms) and the stds of what they fix."""
    poses = np.zeros((n, 4))
    sigma = np.tile([POSITION_SIGMA, POSITION_SIGMA, POSITION_SIGMA, UNKNOWN_YAW_SIGMA], (n, 1))
    for r in range(n):
        tags = np.flatnonzero((tag_robot == r) & placed)
        if tags.size == 0:
            sigma[r, :2] = WIDE_SIGMA
            continue
        arm, pts = arms[tags, :2], points[tags]
        yaw = 0.0
        if tags.size >= 2:
            a, q = arm - arm.mean(axis=0), pts - pts.mean(axis=0)
            yaw = math.atan2(
                float(np.sum(a[:, 0] * q[:, 1] - a[:, 1] * q[:, 0])), float(np.sum(a * q))
            )
            sigma[r, 3] = YAW_SIGMA
        c, s = math.cos(yaw), math.sin(yaw)
        turned = arm @ np.array([[c, s], [-s, c]])
        poses[r, :2] = (pts - turned).mean(axis=0)
        poses[r, 3] = yaw
    return poses, sigma


def _in_frame(poses: FloatArray, ref: FloatArray, turn: float) -> FloatArray:
    """``poses`` relative to ``ref``'s position and yaw, then turned by ``turn`` (the
    reference's yaw hypothesis); heights kept."""
    angle = -ref[3] + turn
    c, s = math.cos(angle), math.sin(angle)
    out = poses.copy()
    dx, dy = poses[:, 0] - ref[0], poses[:, 1] - ref[1]
    out[:, 0], out[:, 1] = c * dx - s * dy, s * dx + c * dy
    out[:, 3] = np.remainder(poses[:, 3] + angle + math.pi, 2.0 * math.pi) - math.pi
    return out
