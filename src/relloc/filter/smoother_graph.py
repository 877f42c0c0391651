"""One fixed-lag smoother of a team's positions, in native GTSAM factors.

The state is one ``Point2`` per robot (the reference included) per smoother step, in a frame
with the shared heading's axes whose origin is the reference's first position (a tight prior on
its first key; it drifts with the reference's random walk, which nothing measures and nothing
reads). Each robot's motion is its own between factor, so a robot without odometry walks on
its own, not in common with every relative position. The published relative position is
``x_k - x_ref``, its covariance from the joint marginal of the two keys. GTSAM's
``IncrementalFixedLagSmoother`` (iSAM2) marginalises what leaves the lag; a step adds a handful
of native factors built from NumPy arrays, so its cost depends on the window, not on the run.

Every factor added is also kept (the small per-step graphs, and the latest value of every key
ever created): :meth:`GraphSmoother.batch` optimises all of them at once afterwards, the
smoothed trajectory of the whole run (nothing of it runs while the smoother is live).
"""

from __future__ import annotations

import gtsam
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

REFERENCE_SIGMA = 1e-4
"""Std (m) of the prior that pins the reference's first key at the origin."""
HUBER_K = 1.345
"""Huber threshold of every range factor, in its sigmas (95 % efficiency on Gaussian noise)."""


def robot_key(step: int, i: int, n: int) -> int:
    """The key of robot ``i`` (team order) at smoother step ``step``."""
    return gtsam.symbol("x", step * n + i)


class GraphSmoother:
    """A fixed-lag smoother of ``n`` robots' positions, ``reference`` the pinned one (module
    docstring)."""

    def __init__(self, n: int, reference: int, lag: float) -> None:
        self.n = n
        self.reference = reference
        self.others = np.array([i for i in range(n) if i != reference], dtype=np.intp)
        self.smoother = gtsam.IncrementalFixedLagSmoother(lag)
        self.step = -1
        self.factors_added = 0
        self.positions: FloatArray = np.zeros((n, 2))
        self.graphs: list[gtsam.NonlinearFactorGraph] = []
        """Every step's factors since the start (for :meth:`batch`)."""
        self.values: dict[int, FloatArray] = {}
        """The latest fixed-lag estimate of every key ever created (where :meth:`batch` starts)."""

    @property
    def estimate(self) -> FloatArray:
        """Each non-reference robot's position relative to the reference ``(N-1, 2)``."""
        return self.positions[self.others] - self.positions[self.reference]

    def keys(self, step: int | None = None) -> list[int]:
        """The robots' keys at ``step`` (default: the latest), team order."""
        s = self.step if step is None else step
        return [robot_key(s, i, self.n) for i in range(self.n)]

    def start(
        self, t: float, mean: FloatArray, cov: FloatArray, index_a: IntArray, index_b: IntArray, distance: FloatArray,
        range_sigma: FloatArray,
    ) -> None:
        """The first step at ``t``: the reference at the origin, each robot ``i`` with a prior at
        ``mean[i]`` (``(N, 2)``, relative to the reference) of covariance ``cov[i]``
        (``(N, 2, 2)``; the reference's is ignored), and the start's ranges (team indices)."""
        self.step = 0
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        keys = self.keys()
        for i, key in enumerate(keys):
            if i == self.reference:
                noise = gtsam.noiseModel.Isotropic.Sigma(2, REFERENCE_SIGMA)
                graph.add(gtsam.PriorFactorPoint2(key, np.zeros(2), noise))
                values.insert(key, np.zeros(2))
            else:
                graph.add(gtsam.PriorFactorPoint2(key, mean[i], gtsam.noiseModel.Gaussian.Covariance(cov[i])))
                values.insert(key, np.asarray(mean[i], float))
            stamps.insert((key, t))
        self._ranges(graph, keys, index_a, index_b, distance, range_sigma)
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
        guess: FloatArray | None = None,
    ) -> None:
        """The next step at ``t``: robot ``i`` moved by ``disp[i]`` (``(N, 2)``) with per-axis
        std ``disp_sigma[i]``; one Huber-robust range factor per pair (team indices
        ``index_a``/``index_b``) of ``distance`` and std ``range_sigma``; ``guess`` ``(N, 2)``:
        where to linearise the new keys (default: the estimate moved by ``disp``)."""
        prev = self.keys()
        self.step += 1
        new = self.keys()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        guess = self.positions + disp if guess is None else guess
        for i in range(self.n):
            noise = gtsam.noiseModel.Isotropic.Sigma(2, float(disp_sigma[i]))
            graph.add(gtsam.BetweenFactorPoint2(prev[i], new[i], np.asarray(disp[i], float), noise))
            values.insert(new[i], np.asarray(guess[i], float))
            stamps.insert((new[i], t))
        self._ranges(graph, new, index_a, index_b, distance, range_sigma)
        self._update(graph, values, stamps)

    @staticmethod
    def _ranges(
        graph: gtsam.NonlinearFactorGraph, keys: list[int], index_a: IntArray, index_b: IntArray, distance: FloatArray,
        range_sigma: FloatArray,
    ) -> None:
        huber = gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K)
        for a, b, d, s in zip(index_a.tolist(), index_b.tolist(), distance.tolist(), range_sigma.tolist(), strict=True):
            noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(1, s))
            graph.add(gtsam.RangeFactor2(keys[a], keys[b], d, noise))

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: gtsam.FixedLagSmootherKeyTimestampMap) -> None:
        self.smoother.update(graph, values, stamps)
        self.factors_added += graph.size()
        self.graphs.append(graph)
        est = self.smoother.calculateEstimate()
        self.values.update(zip(est.keys(), gtsam.utilities.extractPoint2(est), strict=True))
        self.positions = np.array([est.atPoint2(key) for key in self.keys()], float).reshape(self.n, 2)

    def covariances(self) -> FloatArray:
        """Covariance ``(N-1, 2, 2)`` of each robot's latest position relative to the
        reference's: ``S_kk + S_rr - S_kr - S_rk`` of the window's joint marginal."""
        marginals = gtsam.Marginals(self.smoother.getFactors(), self.smoother.calculateEstimate())
        return self._relative_covariances(marginals, self.keys())

    def _relative_covariances(self, marginals: gtsam.Marginals, keys: list[int]) -> FloatArray:
        order = [keys[self.reference], *(keys[i] for i in self.others)]
        full = marginals.jointMarginalCovariance(order).fullMatrix()
        k = self.others.size
        blocks = full.reshape(k + 1, 2, k + 1, 2).transpose(0, 2, 1, 3)
        rr = blocks[0, 0]
        out = np.empty((k, 2, 2))
        for j in range(k):
            out[j] = blocks[j + 1, j + 1] + rr - blocks[j + 1, 0] - blocks[0, j + 1]
        return 0.5 * (out + out.transpose(0, 2, 1))

    def batch(self, steps: list[int], covariances: bool = True) -> tuple[FloatArray, FloatArray | None]:
        """The smoothed trajectory: every factor since the start optimised at once
        (Levenberg-Marquardt from the fixed-lag estimates), each robot's position relative to
        the reference at each of ``steps`` ``(S, N-1, 2)``, and with ``covariances`` their
        covariances ``(S, N-1, 2, 2)`` from the batch graph's joint marginals (else ``None``).
        Raises GTSAM's ``RuntimeError`` where the system is indeterminate."""
        graph = gtsam.NonlinearFactorGraph()
        for g in self.graphs:
            graph.push_back(g)
        initial = gtsam.Values()
        for key, value in self.values.items():
            initial.insert(key, np.asarray(value, float))
        result = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams()).optimize()
        mean = np.empty((len(steps), self.others.size, 2))
        for j, step in enumerate(steps):
            pos = np.array([result.atPoint2(key) for key in self.keys(step)], float).reshape(self.n, 2)
            mean[j] = pos[self.others] - pos[self.reference]
        if not covariances:
            return mean, None
        marginals = gtsam.Marginals(graph, result)
        cov = np.empty((len(steps), self.others.size, 2, 2))
        for j, step in enumerate(steps):
            cov[j] = self._relative_covariances(marginals, self.keys(step))
        return mean, cov

    def cost(self) -> float:
        """The graph's error at the estimate (half the robust chi-square): compares hypotheses
        over the same measurements."""
        return float(self.smoother.getFactors().error(self.smoother.calculateEstimate()))

    def size(self) -> int:
        """Factors the smoother holds now (marginalised ones replaced by their summary)."""
        graph = self.smoother.getFactors()
        return sum(1 for i in range(graph.size()) if graph.exists(i))
