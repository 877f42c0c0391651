"""Consistency of the published covariances: NEES and 95 % coverage against motion capture.

Each estimate that carries a covariance is scored in its own frame (as
:func:`relloc.evaluation.metrics.associate` pairs it): ``NEES = e^T C^-1 e`` of its position
error ``e`` and covariance ``C``, 2 degrees of freedom.
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


@dataclass
class Consistency:
    """Whether the published covariances cover the error: per estimate the normalised
    estimation error squared ``NEES = e^T C^-1 e`` (2 degrees of freedom: mean 2 for a
    consistent filter) and whether the truth lies in the 95 % ellipse (``NEES <= 5.99``)."""

    t: FloatArray
    nees: FloatArray

    @property
    def coverage(self) -> float:
        """Fraction of the estimates whose 95 % ellipse holds the truth."""
        return float(np.mean(self.nees <= CHI2_2D_95)) if self.nees.size else math.nan

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
        t, nees = [], []
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
        if t:
            out[robot] = Consistency(np.array(t), np.array(nees))
    return out
