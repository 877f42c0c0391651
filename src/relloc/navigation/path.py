"""Waypoint paths in the team's relative frame, read from small TOML files.

A path is a polyline of waypoints given, like every relloc estimate, as positions **relative to
the reference robot in the shared heading frame** (the reference robot is the origin, the axes
are those of the team's compass). A rectangle "around the reference robot" is therefore just
four corners around ``(0, 0)``; the robot drives it wherever the reference robot stands.

The derivation: docs/explanation/internals.md, section ``relloc.navigation.path``.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path as FilePath
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from relloc.config import ConfigError

FloatArray = NDArray[np.float64]

__all__ = ["PathError", "WaypointPath", "distance_to_polyline", "load_path"]


class PathError(ConfigError):
    """A path file or path definition is invalid; the message says which key and why."""


_KNOWN_KEYS = {"name", "closed", "reference", "waypoints", "controller", "safety"}


@dataclass(frozen=True)
class WaypointPath:
    """A polyline of waypoints relative to the reference robot (shared heading frame).

    ``closed`` paths return to their first waypoint. ``controller`` and ``safety`` hold the
    overrides read from the file (plain dicts; :mod:`relloc.navigation.controller` and
    :mod:`relloc.navigation.safety` validate them).
    """

    waypoints: tuple[tuple[float, float], ...]
    closed: bool = False
    name: str = "path"
    reference: str = ""
    controller: dict[str, Any] = field(default_factory=dict)
    safety: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.waypoints) < 2:
            raise PathError(
                f"path {self.name!r} needs at least two waypoints, got {len(self.waypoints)}"
            )
        for i, wp in enumerate(self.waypoints):
            if len(wp) != 2 or not all(math.isfinite(c) for c in wp):
                raise PathError(f"waypoints[{i}]: expected two finite numbers, got {wp!r}")
        pts = self.points
        if np.any(np.linalg.norm(np.diff(pts, axis=0), axis=1) < 1e-6):
            raise PathError(f"path {self.name!r} repeats a waypoint (zero-length segment)")

    @classmethod
    def from_points(
        cls, points: ArrayLike, *, closed: bool = False, name: str = "path"
    ) -> WaypointPath:
        """A path from an ``(n, 2)`` array-like of waypoints (validated like a file)."""
        return cls(_parse_waypoints(points), closed=closed, name=name)

    @property
    def points(self) -> FloatArray:
        """The polyline vertices ``(n, 2)``, the first waypoint repeated at the end if closed."""
        pts = np.array(self.waypoints, dtype=float).reshape(-1, 2)
        if self.closed:
            pts = np.vstack([pts, pts[:1]])
        return pts

    @property
    def length(self) -> float:
        """Length of the polyline (m), closing segment included."""
        return float(np.sum(np.linalg.norm(np.diff(self.points, axis=0), axis=1)))

    def distance(self, xy: ArrayLike) -> FloatArray:
        """Distance of each point ``(k, 2)`` to the path (m)."""
        return distance_to_polyline(xy, self.points)


def distance_to_polyline(xy: ArrayLike, vertices: ArrayLike) -> FloatArray:
    """Shortest distance from each point ``(k, 2)`` to a polyline with ``vertices`` ``(n, 2)``."""
    p = np.atleast_2d(np.asarray(xy, dtype=float)).reshape(-1, 2)
    v = np.asarray(vertices, dtype=float).reshape(-1, 2)
    a, b = v[:-1], v[1:]
    ab = b - a  # (s, 2)
    len2 = np.maximum(np.sum(ab**2, axis=1), 1e-18)
    ap = p[:, None, :] - a[None, :, :]  # (k, s, 2)
    u = np.clip(np.sum(ap * ab[None], axis=2) / len2[None], 0.0, 1.0)
    closest = a[None] + u[..., None] * ab[None]
    return np.min(np.linalg.norm(p[:, None, :] - closest, axis=2), axis=1)


def load_path(file: str | FilePath) -> WaypointPath:
    """Read and validate a path TOML file (see the module docstring for the format)."""
    file = FilePath(file)
    try:
        with file.open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise PathError(f"path file not found: {file}") from None
    except tomllib.TOMLDecodeError as exc:
        raise PathError(f"{file}: not valid TOML: {exc}") from None
    try:
        return path_from_dict(data, default_name=file.stem)
    except PathError as exc:
        raise PathError(f"{file}: {exc}") from None


def path_from_dict(data: dict[str, Any], *, default_name: str = "path") -> WaypointPath:
    """Build a path from the parsed TOML table (see :func:`load_path`)."""
    unknown = set(data) - _KNOWN_KEYS
    if unknown:
        raise PathError(f"unknown key(s) {sorted(unknown)}; known: {sorted(_KNOWN_KEYS)}")
    if "waypoints" not in data:
        raise PathError("no 'waypoints' (a list of [x, y] pairs, at least two)")
    closed = data.get("closed", False)
    if not isinstance(closed, bool):
        raise PathError(f"closed: expected true or false, got {closed!r}")
    name = data.get("name", default_name)
    reference = data.get("reference", "")
    for key, value in (("name", name), ("reference", reference)):
        if not isinstance(value, str):
            raise PathError(f"{key}: expected a string, got {value!r}")
    tables = {}
    for key in ("controller", "safety"):
        value = data.get(key, {})
        if not isinstance(value, dict):
            raise PathError(f"[{key}] must be a table, got {value!r}")
        tables[key] = dict(value)
    return WaypointPath(
        _parse_waypoints(data["waypoints"]),
        closed=closed,
        name=name,
        reference=reference,
        controller=tables["controller"],
        safety=tables["safety"],
    )


def _parse_waypoints(raw: Any) -> tuple[tuple[float, float], ...]:
    if isinstance(raw, np.ndarray):
        raw = raw.tolist()
    if not isinstance(raw, Sequence) or isinstance(raw, str):
        raise PathError(f"waypoints: expected a list of [x, y] pairs, got {raw!r}")
    out = []
    for i, wp in enumerate(raw):
        if not isinstance(wp, Sequence) or isinstance(wp, str) or len(wp) != 2:
            raise PathError(f"waypoints[{i}]: expected a pair [x, y], got {wp!r}")
        coords = []
        for j, c in enumerate(wp):
            # bool is an int in Python, and never what a user means by a coordinate
            if isinstance(c, bool) or not isinstance(c, int | float | np.floating | np.integer):
                raise PathError(f"waypoints[{i}][{j}]: expected a number, got {c!r}")
            if not math.isfinite(float(c)):
                raise PathError(f"waypoints[{i}][{j}]: expected a finite number, got {c!r}")
            coords.append(float(c))
        out.append((coords[0], coords[1]))
    if len(out) < 2:
        raise PathError(f"a path needs at least two waypoints, got {len(out)}")
    return tuple(out)
