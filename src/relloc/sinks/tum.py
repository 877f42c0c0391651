"""TUM trajectory files (``t x y z qx qy qz qw``), the format evo and most SLAM tools read.

relloc writes 2-D positions relative to the reference robot: ``z`` is 0 and the orientation the
identity quaternion, so ``evo_ape tum groundtruth_r1.txt pf_r1.txt`` compares positions only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray


def write_tum(path: Path, times: NDArray[np.float64], xy: NDArray[np.float64]) -> None:
    """A TUM trajectory file of 2-D positions, one line per time."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, (x, y) in zip(times, xy, strict=True):
            fh.write(f"{t:.6f} {x:.6f} {y:.6f} 0 0 0 0 1\n")
