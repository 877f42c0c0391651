"""Where a pair's model was trained: the support of its inputs, and a guard outside it.

A range-error model is only known to work on inputs like its training windows; on another
session a pair can see ranges, turns or relative headings it never saw, and a network then
extrapolates (a bidirectional LSTM was measured 0.37 m RMS off on such a pair where the
constant was 0.03). :class:`InputSupport` records, from the training windows, the interval of
each window's last range, of its range and heading rates (per frame: the stage's windows are
frames too) and which cells of the ``(yaw_a, yaw_b)`` torus the last frames occupied; the
stage falls back to the pair's constant for a window outside it (counted ``out_of_support``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

YAW_CELLS = 12
"""Cells per heading axis of the ``(yaw_a, yaw_b)`` occupancy grid (30 degrees each)."""
MARGIN = 0.05
"""Each interval is widened by this share of its width on both sides."""


def _features(windows: NDArray[np.floating[Any]]) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Per window ``(N, n_steps, 3)`` of ``[range, yaw_a, yaw_b]``: ``(N, 4)`` of last range,
    range rate, yaw rates of a and b (per frame), and the ``(yaw_a, yaw_b)`` cell of the last
    frame ``(N,)``."""
    w = np.asarray(windows, dtype=float)
    steps = max(w.shape[1] - 1, 1)
    yaws = np.unwrap(w[:, :, 1:], axis=1)
    rates = np.column_stack(
        [(w[:, -1, 0] - w[:, 0, 0]) / steps, (yaws[:, -1] - yaws[:, 0]) / steps]
    )
    last = np.mod(w[:, -1, 1:] + math.pi, 2 * math.pi)
    cell = np.minimum((last * YAW_CELLS / (2 * math.pi)).astype(np.intp), YAW_CELLS - 1)
    return np.column_stack([w[:, -1, 0], rates]), cell[:, 0] * YAW_CELLS + cell[:, 1]


@dataclass(frozen=True)
class InputSupport:
    """The training inputs' support of one pair (module docstring)."""

    low: tuple[float, float, float, float]
    """Lower bounds of last range, range rate, yaw rate a, yaw rate b (margins included)."""
    high: tuple[float, float, float, float]
    cells: frozenset[int]
    """Occupied ``(yaw_a, yaw_b)`` cells, ``a * YAW_CELLS + b``."""

    @classmethod
    def of(cls, windows: NDArray[np.floating[Any]]) -> InputSupport:
        """The support of training ``windows`` ``(N, n_steps, 3)``; N >= 1."""
        feats, cells = _features(windows)
        lo, hi = feats.min(axis=0), feats.max(axis=0)
        pad = MARGIN * (hi - lo)
        return cls(
            tuple((lo - pad).tolist()), tuple((hi + pad).tolist()), frozenset(cells.tolist())
        )

    def contains(self, windows: NDArray[np.floating[Any]]) -> NDArray[np.bool_]:
        """Per window ``(N, n_steps, 3)``: inside every interval and in an occupied cell."""
        feats, cells = _features(windows)
        inside = np.all((feats >= np.array(self.low)) & (feats <= np.array(self.high)), axis=1)
        return inside & np.isin(cells, list(self.cells))

    def to_json(self) -> dict[str, Any]:
        return {
            "low": list(self.low),
            "high": list(self.high),
            "yaw_cells": YAW_CELLS,
            "cells": sorted(self.cells),
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> InputSupport:
        """Read :meth:`to_json`'s output; raises ``ValueError`` on another grid or shape."""
        if (
            int(data.get("yaw_cells", -1)) != YAW_CELLS
            or len(data["low"]) != 4
            or len(data["high"]) != 4
        ):
            raise ValueError(f"input support of another layout: {data}")
        return cls(
            tuple(float(v) for v in data["low"]),  # type: ignore[arg-type]
            tuple(float(v) for v in data["high"]),  # type: ignore[arg-type]
            frozenset(int(c) for c in data["cells"]),
        )
