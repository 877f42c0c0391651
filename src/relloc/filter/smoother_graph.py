"""One fixed-lag smoother over relative positions, in native GTSAM factors.

The state is one ``Point2`` per non-reference robot per smoother step: its position relative
to the reference robot in the shared heading frame. The reference is one constant key at the
origin, held by a tight prior and kept inside the window by refreshing its timestamp at every
step (so the ranges to it always connect to the same key). GTSAM's
``IncrementalFixedLagSmoother`` (iSAM2) marginalises what leaves the lag; everything a step
adds is a handful of native factors built from NumPy arrays, so the cost of a step depends on
the window, not on how long the run has been.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

REFERENCE_SIGMA = 1e-4
"""Std (m) of the prior that pins the reference key at the origin."""
HUBER_K = 1.345
"""Huber threshold of every range factor, in its sigmas (95 % efficiency on Gaussian noise)."""
REFERENCE_KEY = gtsam.symbol("o", 0)


def robot_key(step: int, k: int, n_others: int) -> int:
    """The key of non-reference robot ``k`` (state order) at smoother step ``step``."""
    return gtsam.symbol("x", step * n_others + k)


class GraphSmoother:
    """A fixed-lag smoother of ``n_others`` relative positions (module docstring)."""

    def __init__(self, n_others: int, lag: float) -> None:
        self.n_others = n_others
        self.smoother = gtsam.IncrementalFixedLagSmoother(lag)
        self.step = -1
        self.factors_added = 0
        self.estimate: FloatArray = np.zeros((n_others, 2))

    def keys(self, step: int | None = None) -> list[int]:
        """The robots' keys at ``step`` (default: the latest)."""
        s = self.step if step is None else step
        return [robot_key(s, k, self.n_others) for k in range(self.n_others)]

    def start(self, t: float, mean: FloatArray, sigma: FloatArray) -> None:
        """The first step at ``t``: the reference at the origin, each robot ``k`` with a prior
        at ``mean[k]`` (``(K, 2)``) of per-axis covariance ``sigma[k]`` (``(K, 2, 2)``)."""
        self.step = 0
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        graph.add(gtsam.PriorFactorPoint2(REFERENCE_KEY, np.zeros(2), gtsam.noiseModel.Isotropic.Sigma(2, REFERENCE_SIGMA)))
        values.insert(REFERENCE_KEY, np.zeros(2))
        stamps.insert((REFERENCE_KEY, t))
        for k, key in enumerate(self.keys()):
            graph.add(gtsam.PriorFactorPoint2(key, mean[k], gtsam.noiseModel.Gaussian.Covariance(sigma[k])))
            values.insert(key, np.asarray(mean[k], float))
            stamps.insert((key, t))
        self._update(graph, values, stamps)

    def advance(
        self,
        t: float,
        disp: FloatArray,
        disp_sigma: FloatArray,
        index_a: IntArray,
        index_b: IntArray,
        distance: FloatArray,
        range_sigma: FloatArray,
        wide: FloatArray,
        guess: FloatArray | None = None,
    ) -> None:
        """The next step at ``t``: robot ``k`` moved by ``disp[k]`` (``(K, 2)``) relative to the
        reference with per-axis std ``disp_sigma[k]``; one Huber-robust range factor per pair
        (state indices ``index_a``/``index_b``, ``-1`` the reference) of ``distance`` and std
        ``range_sigma``; robots with ``wide[k] > 0`` get a prior of that std (m) about their
        predicted position (none of their ranges has placed them yet); ``guess`` ``(K, 2)``:
        where to linearise the new keys (default: the estimate moved by ``disp``)."""
        prev = self.keys()
        self.step += 1
        new = self.keys()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        stamps.insert((REFERENCE_KEY, t))
        guess = self.estimate + disp if guess is None else guess
        for k in range(self.n_others):
            noise = gtsam.noiseModel.Isotropic.Sigma(2, float(disp_sigma[k]))
            graph.add(gtsam.BetweenFactorPoint2(prev[k], new[k], np.asarray(disp[k], float), noise))
            values.insert(new[k], np.asarray(guess[k], float))
            stamps.insert((new[k], t))
            if wide[k] > 0.0:
                graph.add(gtsam.PriorFactorPoint2(new[k], guess[k], gtsam.noiseModel.Isotropic.Sigma(2, float(wide[k]))))
        for a, b, d, s in zip(index_a.tolist(), index_b.tolist(), distance.tolist(), range_sigma.tolist(), strict=True):
            ka = REFERENCE_KEY if a < 0 else new[a]
            kb = REFERENCE_KEY if b < 0 else new[b]
            noise = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K), gtsam.noiseModel.Isotropic.Sigma(1, s)
            )
            graph.add(gtsam.RangeFactor2(ka, kb, d, noise))
        self._update(graph, values, stamps)

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: gtsam.FixedLagSmootherKeyTimestampMap) -> None:
        self.smoother.update(graph, values, stamps)
        self.factors_added += graph.size()
        est = self.smoother.calculateEstimate()
        self.estimate = np.array([est.atPoint2(key) for key in self.keys()], float).reshape(self.n_others, 2)

    def covariances(self) -> FloatArray:
        """Marginal covariance ``(K, 2, 2)`` of each robot's latest position (relative to the
        pinned reference, so already relative)."""
        return np.array([self.smoother.marginalCovariance(key) for key in self.keys()], float).reshape(self.n_others, 2, 2)

    def cost(self) -> float:
        """The graph's error at the estimate (half the robust chi-square): compares hypotheses
        over the same measurements."""
        return float(self.smoother.getFactors().error(self.smoother.calculateEstimate()))

    def size(self) -> int:
        """Factors the smoother holds now (marginalised ones replaced by their summary)."""
        graph = self.smoother.getFactors()
        return sum(1 for i in range(graph.size()) if graph.exists(i))


def relative_sigma(own: float, reference: float, floor: float) -> float:
    """Per-axis std of a relative displacement from the two robots' own stds and a floor."""
    return math.sqrt(own * own + reference * reference + floor * floor)
