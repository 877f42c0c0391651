"""Independent, seeded random streams: one per quantity and owner.

Every random quantity of the simulator comes from its own sub-stream of
``numpy.random.default_rng``, keyed by the seed, what it is and whose it is (e.g. the noise of
the UWB pair ``n_1-n_3``). Switching detections on, adding a robot or lengthening the run
therefore does not change the UWB noise of an existing pair.
"""

from __future__ import annotations

import zlib

import numpy as np


def stream(seed: int, *names: str) -> np.random.Generator:
    """An independent random stream for ``names`` (e.g. ``("uwb-noise", "n_1-n_3")``)."""
    key = tuple(zlib.crc32(n.encode()) for n in names)
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=key))
