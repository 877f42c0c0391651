"""Consistency of the published covariances: NEES and 95 % coverage against motion capture.

Each estimate that carries a covariance is scored in its own frame (as
:func:`relloc.evaluation.metrics.associate` pairs it): ``NEES = e^T C^-1 e`` of its position
error ``e`` and covariance ``C``, as many degrees of freedom as the position has dimensions
(2, or 3 for a flying team's estimates).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from relloc.estimate import Estimate
from relloc.evaluation.metrics import FloatArray, GroundTruth, truth_in_frame

CHI2_2D_95 = 5.991464547107979
"""95 % quantile of the chi-square distribution with 2 degrees of freedom: the squared
Mahalanobis radius of a 2D 95 % ellipse."""
CHI2_3D_95 = 7.814727903251179
"""The same with 3 degrees of freedom: a 3D 95 % ellipsoid."""
CHI2_95 = {2: CHI2_2D_95, 3: CHI2_3D_95}
"""The 95 % quantile by degrees of freedom (the positions' dimension)."""


@dataclass
class Consistency:
    """Whether the published covariances cover the error: per estimate the normalised
    estimation error squared ``NEES = e^T C^-1 e`` (``dof`` degrees of freedom, the positions'
    dimension: mean ``dof`` for a consistent filter) and whether the truth lies in the 95 %
    ellipse (``NEES <= 5.99`` in 2D) or ellipsoid (``NEES <= 7.81`` in 3D)."""

    t: FloatArray
    nees: FloatArray
    dof: int = 2

    @property
    def coverage(self) -> float:
        """Fraction of the estimates whose 95 % ellipse (ellipsoid) holds the truth."""
        return float(np.mean(self.nees <= CHI2_95[self.dof])) if self.nees.size else math.nan

    @property
    def nees_median(self) -> float:
        return float(np.median(self.nees)) if self.nees.size else math.nan

    @property
    def nees_mean(self) -> float:
        return float(np.mean(self.nees)) if self.nees.size else math.nan


def consistency(
    estimates: Sequence[Estimate],
    gt: GroundTruth,
    robots: Iterable[str],
    t_start: float,
    rotation: float = 0.0,
) -> dict[str, Consistency]:
    """NEES of every estimate from ``t_start`` on that carries a covariance, per robot, against
    interpolated relative ground truth in the estimate's frame (as in :func:`associate`).
    Methods without covariances (multilateration) get none."""
    out: dict[str, Consistency] = {}
    for robot in robots:
        t, nees, dof = [], [], 2
        for est in estimates:
            if est.t < t_start or robot not in est.positions or robot not in est.covariances:
                continue
            truth = truth_in_frame(est, gt, robot, rotation)
            if truth is None:
                continue
            e = np.subtract(est.positions[robot], truth)
            cov = np.array(est.covariances[robot], float)
            if not np.all(np.isfinite(cov)) or np.linalg.det(cov) <= 0.0:
                continue
            t.append(est.t)
            nees.append(float(e @ np.linalg.solve(cov, e)))
            dof = len(e)
        if t:
            out[robot] = Consistency(np.array(t), np.array(nees), dof)
    return out
