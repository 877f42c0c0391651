"""The estimate every localizer emits: positions relative to the reference robot, with their
covariances and, where a method estimates them, headings, biases and odometry scales.

It is vocabulary, like the events: stages (association gates on it), sinks, evaluation and
navigation read it without depending on the localizers that produce it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Estimate:
    """Positions of every non-reference robot relative to the reference, in the shared heading
    frame (heading-estimate mode: the reference robot's odometry frame)."""

    t: float
    method: str
    reference: str
    positions: dict[str, tuple[float, float]]
    covariances: dict[str, tuple[tuple[float, float], tuple[float, float]]] = field(
        default_factory=dict
    )
    ess: float | None = None
    headings: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Heading-estimate mode: per robot, the rotation that takes its odometry displacements
    into the reference robot's odometry frame, as (circular mean, circular std) in rad. A
    spread near pi says the heading is unobservable so far (the robot has not moved). The
    reference's own entry starts at 0 (by definition) and follows its odometry's drift."""
    biases: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Online-bias mode: per UWB node pair, the range bias (mean, std) in m. A std still at its
    prior says the bias is unobservable so far (the pair's distance has not changed)."""
    scales: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Online-scale mode: per robot, the odometry scale (mean, std)."""
    recovering: bool = False
    """The localizer found itself lost (most of a robot's ranges disagree with the estimate)
    and is re-injecting hypotheses: the positions are not to be trusted until it clears."""

    def std(self, robot: str) -> float:
        """Position standard deviation of ``robot``: sqrt of the covariance's largest eigenvalue."""
        cov = self.covariances.get(robot)
        if cov is None:
            return math.nan
        return float(np.sqrt(np.max(np.linalg.eigvalsh(np.array(cov)))))
