"""TUM trajectory files (``t x y z qx qy qz qw``), the format evo and most SLAM tools read.

relloc writes positions relative to the reference robot, as it publishes them: ``z`` the
position's own in 3D, 0 in 2D, and the orientation the identity quaternion, so ``evo_ape tum
groundtruth_r1.txt pf_r1.txt`` compares positions only; where a robot's yaw is published (a
flying team's 3D estimates, :attr:`relloc.evaluation.report.MethodReport.published_yaws`) the
quaternion is that yaw about z. Where the formation's orientation was not observable the
positions are the formation in its gauge (frame ``<reference>/formation``; align it, ``evo_ape
-as``), and a ``# frames:`` comment names the frames the file holds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

IDENTITY = "0 0 0 1"
"""The quaternion ``qx qy qz qw`` of a line without a yaw."""


def write_tum(
    path: Path,
    times: NDArray[np.float64],
    positions: NDArray[np.float64],
    frames: Sequence[str] = (),
    yaws: NDArray[np.float64] | None = None,
) -> None:
    """A TUM trajectory file of positions ``(N, 2)`` or ``(N, 3)``, one line per time; the
    ``frames`` the positions are in (ROS frame ids) named in a comment where there is more than
    the reference's own; ``yaws`` (rad, ``(N,)``, NaN where none) the orientations, else the
    identity."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        if len(frames) > 1 or any(f.endswith("/formation") for f in frames):
            fh.write(f"# frames: {', '.join(frames)}\n")
        turns = [math.nan] * len(times) if yaws is None else yaws.tolist()
        for t, p, yaw in zip(times, positions, turns, strict=True):
            z = f"{p[2]:.6f}" if len(p) > 2 else "0"
            fh.write(f"{t:.6f} {p[0]:.6f} {p[1]:.6f} {z} {_quaternion(yaw)}\n")


def _quaternion(yaw: float) -> str:
    """``qx qy qz qw`` of a rotation ``yaw`` about z (the identity for NaN)."""
    if not math.isfinite(yaw):
        return IDENTITY
    return f"0 0 {math.sin(yaw / 2.0):.6f} {math.cos(yaw / 2.0):.6f}"
