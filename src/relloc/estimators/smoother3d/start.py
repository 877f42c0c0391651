"""The 3D smoother's start: level poses from the start window's ranges and heights.

With heights (:func:`level_start`), each tag is a point at its robot's height plus its lever
arm's z. A range's horizontal part ``sqrt(d^2 - dz^2)`` between two tags, with each robot's
own tags held at their arms' horizontal distance, is a planar range graph: its shape
(:func:`relloc.filter.range_shape.shape_from_ranges`) places every tag. Without any height,
the tags' shape is found in 3D (classical scaling, then SMACOF) and "up" is the direction
across which every robot's tags, level on a level robot, lie flattest: the least eigenvector
of the spread of their differences; its sign is a guess (ranges never tell up from down, so a
second hypothesis takes the other). A robot's yaw and position are the rigid fit of its arms
onto its tags (one tag: the yaw is unknown, 0 with a wide std). Put in the reference's frame,
that is one hypothesis; the mirror image of the shape is another (ranges never tell them
apart; motion does), and where the reference's tags do not fix its yaw, ``ROTATIONS`` turns
of each. Where tags fix no yaw well (two tags close together, unknown pair biases), a team
with odometry takes its yaws from its motion instead (:func:`yaws_from_motion`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from relloc import geometry
from relloc.filter.range_shape import (
    classical_mds,
    distance_matrix,
    shape_from_ranges,
    shortest_paths,
    smacof,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

ROTATIONS = 8
"""Yaw hypotheses per handedness where the reference's tags do not fix its yaw."""
YAW_TRUST = 0.3
"""Largest std (rad) of the reference's yaw from its tags that a single turn is trusted with."""
POSITION_SIGMA = 0.3
"""Smallest std (m per axis) of a started robot's position."""
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
    yaw_sigma: FloatArray,
) -> tuple[FloatArray, FloatArray, float] | None:
    """Hypotheses ``(M, N, 4)`` of every robot's ``(x, y, z, yaw)`` relative to the
    reference's position and yaw, their stds ``(M, N, 4)`` and the shape's RMS residual, from
    the tags' robots ``tag_robot`` ``(P,)``, lever arms ``(P, 3)``, the robots' heights
    ``(N,)`` (NaN where a robot has none; all NaN: no heights at all), the tag ranges
    ``(tag_a, tag_b, distance)`` and the std of the yaw each robot's tags give ``(N,)`` (the
    reference's above ``YAW_TRUST``: ``ROTATIONS`` turns); ``None`` where no range places the
    reference's tags."""
    n = heights.size
    p = tag_robot.size
    ta, tb, d = ranges
    same = [(i, j) for i in range(p) for j in range(i + 1, p) if tag_robot[i] == tag_robot[j]]
    si = np.array([i for i, _ in same], np.intp)
    sj = np.array([j for _, j in same], np.intp)
    ia, ib = np.concatenate([ta, si]), np.concatenate([tb, sj])
    ref_tags = np.flatnonzero(tag_robot == reference)
    if np.all(np.isnan(heights)):
        placed_3d = _shape_3d(p, ia, ib, np.concatenate([d, geometry.distance(arms[si], arms[sj])]))
        if placed_3d is None:
            return None
        points, placed, rms = placed_3d
        up = _up(points, placed, si, sj)
        layouts = [_level(points, up * sign, tag_robot, arms, n) for sign in (1.0, -1.0)]
    else:
        heights = np.where(np.isnan(heights), 0.0, heights)
        tag_z = heights[tag_robot] + arms[:, 2]
        dz = tag_z[ta] - tag_z[tb]
        flat = np.sqrt(np.maximum(d * d - dz * dz, 1e-4))
        rigid = geometry.distance(arms[si, :2], arms[sj, :2])
        shape = shape_from_ranges(p, int(ref_tags[0]), ia, ib, np.concatenate([flat, rigid]))
        if shape.measured == 0:
            return None
        points, placed, rms = shape.relative, shape.placed, shape.rms
        layouts = [(points, heights)]
    if not placed[ta].any():
        return None
    turns = 1 if ref_tags.size >= 2 and yaw_sigma[reference] <= YAW_TRUST else ROTATIONS
    hypotheses, stds = [], []
    for flat_points, z in layouts:
        for mirror in (1.0, -1.0):
            poses, sigma = _fit(
                flat_points * np.array([1.0, mirror]), placed, tag_robot, arms, yaw_sigma
            )
            poses[:, 2] = z
            ref = poses[reference].copy()
            for k in range(turns):
                turn = 2.0 * math.pi * k / turns
                hypotheses.append(_in_frame(poses, ref, turn))
                stds.append(sigma)
    position = max(POSITION_SIGMA, 2.0 * rms)
    out_sigma = np.array(stds)
    out_sigma[..., :3] = np.maximum(out_sigma[..., :3], position)
    return np.array(hypotheses), out_sigma, float(rms)


def _shape_3d(
    p: int, ia: IntArray, ib: IntArray, d: FloatArray
) -> tuple[FloatArray, NDArray[np.bool_], float] | None:
    """The tags' shape in 3D ``(P, 3)`` (classical scaling of the completed distances, then
    SMACOF on the measured ones), which tags it placed, its RMS residual; ``None``: too few."""
    dist, known = distance_matrix(p, ia, ib, d)
    paths = shortest_paths(dist, known)
    placed = np.isfinite(paths[0]) if np.isfinite(paths).any() else np.zeros(p, bool)
    idx = np.flatnonzero(placed)
    if idx.size < 4:
        return None
    sub, w = paths[np.ix_(idx, idx)], known[np.ix_(idx, idx)].astype(float)
    x = smacof(sub, w, classical_mds(sub, dims=3))
    points = np.zeros((p, 3))
    points[idx] = x
    res = (geometry.distance(x[:, None, :], x[None, :, :]) - sub)[w > 0]
    return points, placed, float(np.sqrt(np.mean(res * res))) if res.size else 0.0


def chiral(tag_robot: IntArray, arms: FloatArray) -> bool:
    """Whether some robot's tags are three or more, not on one line in the plane: a mirror
    image of the formation would need their mirror image, so they tell the handedness (once
    the ranges have placed them well: the start keeps both hypotheses, the graph's cost
    chooses)."""
    for r in np.unique(tag_robot).tolist():
        flat = arms[tag_robot == r, :2]
        if flat.shape[0] >= 3 and np.linalg.matrix_rank(flat - flat.mean(axis=0), tol=1e-3) == 2:
            return True
    return False


def _up(points: FloatArray, placed: NDArray[np.bool_], si: IntArray, sj: IntArray) -> FloatArray:
    """The unit direction across which the differences of every robot's tags (pairs ``si``,
    ``sj``) spread least: level tags lie across "up" (z for an unknown shape: no robot has
    two placed tags)."""
    keep = placed[si] & placed[sj]
    diff = points[sj[keep]] - points[si[keep]]
    if diff.shape[0] < 2:
        return np.array([0.0, 0.0, 1.0])
    _, vecs = np.linalg.eigh(diff.T @ diff)
    return np.asarray(vecs[:, 0], float)


def _level(
    points: FloatArray, up: FloatArray, tag_robot: IntArray, arms: FloatArray, n: int
) -> tuple[FloatArray, FloatArray]:
    """The 3D tag ``points`` turned so that ``up`` is +z: their planar part ``(P, 2)`` and each
    robot's height ``(N,)`` (its tags' mean z less their arms' z), relative to the first."""
    z = up / np.linalg.norm(up)
    x = np.cross([0.0, 1.0, 0.0], z) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    level = points @ np.stack([x, np.cross(z, x), z], axis=1)
    heights = np.array(
        [
            float(np.mean(level[tag_robot == r, 2] - arms[tag_robot == r, 2]))
            if np.any(tag_robot == r)
            else 0.0
            for r in range(n)
        ]
    )
    return level[:, :2], heights - heights[0]


def _fit(
    points: FloatArray,
    placed: NDArray[np.bool_],
    tag_robot: IntArray,
    arms: FloatArray,
    yaw_sigma: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Each robot's ``(x, y, 0, yaw)`` from its tags' planar ``points`` (the rigid fit of its
    arms) and the stds of what they fix (a yaw ``yaw_sigma``'s, where two tags are placed)."""
    n = yaw_sigma.size
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
            sigma[r, 3] = min(float(yaw_sigma[r]), UNKNOWN_YAW_SIGMA)
        c, s = math.cos(yaw), math.sin(yaw)
        turned = arm @ np.array([[c, s], [-s, c]])
        poses[r, :2] = (pts - turned).mean(axis=0)
        poses[r, 3] = yaw
    return poses, sigma


def in_reference_frame(poses: FloatArray, reference: int) -> FloatArray:
    """``poses`` ``(N, 4)`` relative to robot ``reference``'s position and yaw."""
    return _in_frame(poses, poses[reference].copy(), 0.0)


def _in_frame(poses: FloatArray, ref: FloatArray, turn: float) -> FloatArray:
    """``poses`` relative to ``ref``'s position and yaw, the others then turned by ``turn``
    about the reference (its yaw hypothesis: the reference stays at yaw 0); heights kept."""
    angle = -ref[3] + turn
    c, s = math.cos(angle), math.sin(angle)
    out = poses.copy()
    dx, dy = poses[:, 0] - ref[0], poses[:, 1] - ref[1]
    out[:, 0], out[:, 1] = c * dx - s * dy, s * dx + c * dy
    out[:, 3] = np.remainder(poses[:, 3] + angle + math.pi, 2.0 * math.pi) - math.pi
    out[np.all(poses == ref, axis=1), 3] = 0.0
    return out


def yaws_from_motion(
    positions: FloatArray, odometry: FloatArray, moving: NDArray[np.bool_]
) -> tuple[FloatArray, bool, float]:
    """Each moving robot's yaw at the last of ``S`` steps, from where a graph of ranges alone
    placed it ``positions`` ``(S, N, 2)`` and where its odometry ``(S, N, 3)`` (its own frame:
    x, y, yaw) says it went: the rotation that best turns its odometry displacements onto its
    placed ones, plus its odometry yaw then (NaN for a robot not ``moving``). The graph's
    positions may be the mirror image of the truth (ranges alone never tell): the handedness
    whose rotations fit best is taken, ``True`` where it is the mirror (negate y). Also the
    fit's RMS residual (m)."""
    best: tuple[FloatArray, bool, float] | None = None
    for mirror in (False, True):
        placed = positions * np.array([1.0, -1.0 if mirror else 1.0])
        yaws = np.full(positions.shape[1], math.nan)
        squares, count = 0.0, 0
        for i in np.flatnonzero(moving).tolist():
            dp = placed[:, i] - placed[0, i]
            dq = odometry[:, i, :2] - odometry[0, i, :2]
            theta = math.atan2(
                float(np.sum(dq[:, 0] * dp[:, 1] - dq[:, 1] * dp[:, 0])), float(np.sum(dq * dp))
            )
            c, s = math.cos(theta), math.sin(theta)
            turned = dq @ np.array([[c, s], [-s, c]])
            squares += float(np.sum((dp - turned) ** 2))
            count += dp.shape[0]
            yaws[i] = math.remainder(theta + float(odometry[-1, i, 2]), math.tau)
        rms = math.sqrt(squares / max(count, 1))
        if best is None or rms < best[2]:
            best = (yaws, mirror, rms)
    assert best is not None
    return best
