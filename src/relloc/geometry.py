"""Geometry in one place: where a tag is, the distance between two points and its Jacobian.

Points are arrays whose coordinate axis has a dimension (2 today: ``(x, y)``; a last axis by
default, or the one named). Every estimator, multilateration and the calibration compute a
range through these functions, so that a tag's lever arm or a third dimension changes this
module, not five.

* :func:`tag_position`: a tag carried at ``lever_arm`` in a robot's body frame, at the robot's
  position and yaw (a yaw-only rotation: about z in 3D).
* :func:`norm`, :func:`distance`: the Euclidean length of a difference, and of ``a - b``.
* :func:`direction`: the unit vector of a difference, the Jacobian of a range:
  ``d|a - b| / da = u^T``, ``d|a - b| / db = -u^T``.

The sums are in coordinate order, so a 2D distance is ``sqrt(dx * dx + dy * dy)`` to the bit
whatever the call site's layout (a coordinate axis first, as the particle filter stores its
particles, or last).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def tag_position(position: ArrayLike, yaw: ArrayLike, lever_arm: ArrayLike) -> FloatArray:
    """Where a tag is: ``position + R(yaw) lever_arm`` (positions ``(..., D)``, yaws ``(...)``,
    the lever arm ``(D,)`` in the body frame; ``R`` turns x and y, z is kept)."""
    p = np.asarray(position, float)
    arm = np.asarray(lever_arm, float)
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.array(p, dtype=float, copy=True)
    out[..., 0] += c * arm[0] - s * arm[1]
    out[..., 1] += s * arm[0] + c * arm[1]
    if arm.shape[0] > 2:
        out[..., 2:] += arm[2:]
    return out


def norm(diff: FloatArray, axis: int = -1, *, overwrite: bool = False) -> FloatArray:
    """``|diff|`` along the coordinate ``axis``; ``overwrite``: square ``diff`` in place (a hot
    path's temporary, saving an allocation)."""
    sq = diff if overwrite else np.array(diff, dtype=float, copy=True)
    sq *= sq
    return np.sqrt(np.sum(sq, axis=axis))


def distance(a: ArrayLike, b: ArrayLike, axis: int = -1) -> FloatArray:
    """``|a - b|`` along the coordinate ``axis``."""
    return norm(np.subtract(a, b, dtype=float), axis, overwrite=True)


def direction(
    diff: FloatArray, *, floor: float = 1e-6, fallback: ArrayLike | None = None
) -> tuple[FloatArray, FloatArray]:
    """``(|diff|, u)`` along the last axis, ``u = diff / max(|diff|, floor)``: the Jacobian of
    ``|a - b|`` with respect to ``a`` (``diff = a - b``). Where ``|diff| <= floor`` the
    direction is not defined: ``u`` is ``fallback`` (a unit vector) if one is given, else the
    short vector the division gives (a range then moves nothing in a linearised update)."""
    dist = norm(diff)
    u = diff / np.maximum(dist, floor)[..., None]
    if fallback is not None:
        u = np.where((dist > floor)[..., None], u, np.asarray(fallback, float))
    return dist, u
