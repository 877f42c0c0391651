"""The covariance floor of a team without UWB: one sighting's noise, learnt from the sightings.

Every filter adds a floor to the covariances it publishes (:mod:`relloc.filter.summary`): the
error of one relative measurement, which fusing many cannot average away, since their errors
are correlated in time. With UWB it is one range's noise (``[uwb]``, set by the localizer). A
team whose robots carry no UWB node localizes from sightings alone (MRCLAM's cameras), and
their noise is what each sighting states: range ``sigma_range`` along the line of sight,
``range * sigma_bearing`` across it. The floor is the median over the sightings fused so far
of that noise per axis, ``(sigma_range^2 + (range * sigma_bearing)^2) / 2``: the sensor's own
figure, not a value fitted to a recording.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from relloc.config import TeamConfig

__all__ = ["SightingFloor"]

KEPT = 2000
"""Sightings the median is taken over (the most recent)."""


class SightingFloor:
    """The floor from the sightings of a team without UWB (module docstring)."""

    def __init__(self, config: TeamConfig) -> None:
        self.active = not any(r.nodes for r in config.robots)
        """Whether the team has no UWB node (else the floor is one range's noise)."""
        self._noise: deque[float] = deque(maxlen=KEPT)

    def observe(self, batch: list[Any], current: float) -> float:
        """The floor after fusing ``batch``: ``current`` until a sighting with a range came."""
        if not self.active:
            return current
        added = False
        for m in batch:
            r, sr, sb = (
                getattr(m, "range", None),
                getattr(m, "sigma_range", None),
                getattr(m, "sigma_bearing", None),
            )
            if r is None or sr is None or sb is None or not hasattr(m, "observer"):
                continue
            self._noise.append(0.5 * (sr * sr + (r * sb) ** 2))
            added = True
        if not self._noise:
            return current
        return float(np.median(self._noise)) if added else current
