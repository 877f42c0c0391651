"""One fixed-lag smoother of a team's positions, in native GTSAM factors.

The state is one ``Point2`` per robot (the reference included) per smoother step, in a frame
with the shared heading's axes whose origin is the reference's first position (a tight prior on
its first key; it drifts with the reference's random walk, which nothing measures and nothing
reads). Each robot's motion is its own between factor, so a robot without odometry walks on
its own, not in common with every relative position. The published relative position is
``x_k - x_ref``, its covariance from the joint marginal of the two keys. A measured relative
position (:class:`Relative`) is a native between factor of the two robots' keys. GTSAM's
``IncrementalFixedLagSmoother`` (iSAM2) marginalises what leaves the lag; a step adds a handful
of native factors built from NumPy arrays, so its cost depends on the window, not on the run.

Every factor added is also kept (the small per-step graphs, and the latest value of every key
ever created): :meth:`GraphSmoother.batch` optimises all of them at once afterwards, the
smoothed trajectory of the whole run (nothing of it runs while the smoother is live).

**Online biases**: a ``Vector1`` key per node pair whose bias is estimated, and a range factor
``|p_a - p_b| + b - z`` (a Python ``CustomFactor``, Huber-robust too; GTSAM has no native one,
and a Python callback is slow, so pairs with a fixed bias keep the native ``RangeFactor2``).
The prior (:class:`relloc.localizers.priors.BiasPrior`): a ``Vector1`` key ``o`` per shared
offset, ``N(0, sigma_l^2)``, and per pair a factor ``b - sum(o_l) - mean ~ N(0, sigma^2)`` over
the offsets it shares. Biases and offsets are constant: their keys' timestamps are refreshed
every step, so the lag never marginalises a key later factors reference, and what leaves the
window stays in their marginal. (A random walk, a new key
tied to the last by a between factor, makes iSAM2's marginalisation of the old keys fail as
indeterminate within a lag, GTSAM's known fixed-lag marginalisation bugs.)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular

from relloc import geometry
from relloc.filter.factors import RangeTerms
from relloc.localizers.priors import BiasPrior

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

REFERENCE_SIGMA = 1e-4
"""Std (m) of the prior that pins the reference's first key at the origin."""
HUBER_K = 1.345
"""Huber threshold of every range factor, in its sigmas (95 % efficiency on Gaussian noise)."""


@dataclass(frozen=True)
class Relative:
    """Measured relative positions ``p_target - p_observer`` in the shared heading frame (a
    sighting's range and bearing, two robots' detections of one object), team indices."""

    observer: IntArray
    target: IntArray
    vector: FloatArray
    """``(K, 2)``."""
    cov: FloatArray
    """``(K, 2, 2)``: each vector's covariance."""

    @property
    def size(self) -> int:
        return int(self.observer.size)


def robot_key(step: int, i: int, n: int) -> int:
    """The key of robot ``i`` (team order) at smoother step ``step``."""
    return gtsam.symbol("x", step * n + i)


BIAS_CHR = ord("b")
"""The symbol character of the bias keys (``gtsam.symbol("b", j)``, ``j`` counting them)."""
OFFSET_CHR = ord("o")
"""The symbol character of the shared offsets' keys."""


def _deviation(
    mean: float,
) -> Callable[[gtsam.CustomFactor, gtsam.Values, list[FloatArray] | None], FloatArray]:
    """The error of a pair's own deviation, keys ``(b, o_1, ..., o_k)``: ``b - sum(o) - mean``."""

    def error(
        factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[FloatArray] | None
    ) -> FloatArray:
        keys = factor.keys()
        if jacobians is not None:
            jacobians[0] = np.ones((1, 1))
            for i in range(1, len(keys)):
                jacobians[i] = -np.ones((1, 1))
        shared = sum(values.atVector(k)[0] for k in keys[1:])
        return np.array([values.atVector(keys[0])[0] - shared - mean])

    return error


def _biased_range(
    distance: float,
) -> Callable[[gtsam.CustomFactor, gtsam.Values, list[FloatArray] | None], FloatArray]:
    """The error of a range ``distance`` between keys ``(p_a, p_b, b)``: ``|p_a - p_b| + b - z``
    with Jacobians ``u^T``, ``-u^T``, ``1`` (``u`` the unit vector from ``p_b`` to ``p_a``, an
    arbitrary unit vector where they coincide)."""

    def error(
        factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[FloatArray] | None
    ) -> FloatArray:
        ka, kb, kbias = factor.keys()
        dist, u = geometry.direction(
            values.atPoint2(ka) - values.atPoint2(kb), floor=1e-9, fallback=(1.0, 0.0)
        )
        if jacobians is not None:
            jacobians[0] = u.reshape(1, 2)
            jacobians[1] = -u.reshape(1, 2)
            jacobians[2] = np.ones((1, 1))
        return np.array([float(dist) + values.atVector(kbias)[0] - distance])

    return error


def add_bias_prior(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    stamps: gtsam.FixedLagSmootherKeyTimestampMap,
    t: float,
    prior: BiasPrior,
    bias_keys: list[int],
    offset_keys: list[int],
) -> None:
    """``prior`` on the online biases' keys ``bias_keys`` and its shared offsets'
    ``offset_keys`` (module docstring): every key inserted at its prior mean, stamped ``t``."""
    rows_v = zip(offset_keys, prior.offset_mean.tolist(), prior.latent_sigma.tolist(), strict=True)
    for key, m0, sd in rows_v:
        noise = gtsam.noiseModel.Isotropic.Sigma(1, sd)
        graph.add(gtsam.PriorFactorVector(key, np.array([m0]), noise))
        values.insert(key, np.array([m0]))
        stamps.insert((key, t))
    rows = zip(
        bias_keys,
        prior.mean.tolist(),
        prior.marginal_mean.tolist(),
        prior.sigma.tolist(),
        prior.loading > 0,
        strict=True,
    )
    for key, m, start, sd, shares in rows:
        noise = gtsam.noiseModel.Isotropic.Sigma(1, sd)
        offsets = [k for k, on in zip(offset_keys, shares.tolist(), strict=True) if on]
        graph.add(gtsam.CustomFactor(noise, [key, *offsets], _deviation(m)))
        values.insert(key, np.array([start]))
        stamps.insert((key, t))


class GraphSmoother:
    """A fixed-lag smoother of ``n`` robots' positions, ``reference`` the pinned one (module
    docstring)."""

    def __init__(
        self,
        n: int,
        reference: int,
        lag: float,
        biases: BiasPrior | None = None,
        record: bool = True,
    ) -> None:
        """``biases``: the prior of the online biases (none by default); ``record``: keep
        every factor and key for :meth:`batch` (a live server's window keeps none)."""
        self.record = record
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
        self.prior = biases
        self.bias_mean = np.zeros(0) if biases is None else biases.mean
        self.bias_keys = [gtsam.symbol("b", j) for j in range(self.bias_mean.size)]
        """Each online bias's key."""
        latents = 0 if biases is None else biases.latent_sigma.size
        self.offset_keys = [gtsam.symbol("o", j) for j in range(latents)]
        """Each shared offset's key."""
        self.biases: FloatArray = self.bias_mean.copy()
        """Each online bias's latest estimate."""
        self._estimate = gtsam.Values()
        """The window's estimate after the last update."""
        self._joint: FloatArray | None = None
        """:meth:`_window_joint` of the last update (computed when first asked)."""

    @property
    def estimate(self) -> FloatArray:
        """Each non-reference robot's position relative to the reference ``(N-1, 2)``."""
        return self.positions[self.others] - self.positions[self.reference]

    def keys(self, step: int | None = None) -> list[int]:
        """The robots' keys at ``step`` (default: the latest), team order."""
        s = self.step if step is None else step
        return [robot_key(s, i, self.n) for i in range(self.n)]

    def start(
        self,
        t: float,
        mean: FloatArray,
        cov: FloatArray,
        *,
        ranges: RangeTerms,
        relative: Relative | None = None,
    ) -> None:
        """The first step at ``t``: the reference at the origin, each robot ``i`` with a prior at
        ``mean[i]`` (``(N, 2)``, relative to the reference) of covariance ``cov[i]``
        (``(N, 2, 2)``; the reference's is ignored), each online bias at its prior, and the
        start's ``ranges`` and ``relative`` observations."""
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
                graph.add(
                    gtsam.PriorFactorPoint2(
                        key, mean[i], gtsam.noiseModel.Gaussian.Covariance(cov[i])
                    )
                )
                values.insert(key, np.asarray(mean[i], float))
            stamps.insert((key, t))
        self._bias_priors(graph, values, stamps, t)
        self._ranges(graph, keys, ranges)
        self._relatives(graph, keys, relative)
        self._update(graph, values, stamps)

    def advance(
        self,
        t: float,
        disp: FloatArray,
        disp_sigma: FloatArray,
        *,
        ranges: RangeTerms,
        guess: FloatArray | None = None,
        relative: Relative | None = None,
    ) -> None:
        """The next step at ``t``: robot ``i`` moved by ``disp[i]`` (``(N, 2)``) with per-axis
        std ``disp_sigma[i]``; one Huber-robust range factor per range term (one per pair,
        its online bias where it has one: module docstring); ``guess`` ``(N, 2)``: where to
        linearise the new keys (default: the estimate moved by ``disp``); ``relative``:
        measured relative positions (sightings, detections, plug-ins)."""
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
        for key in [*self.bias_keys, *self.offset_keys]:
            stamps.insert((key, t))  # kept in the window (module docstring)
        self._ranges(graph, new, ranges)
        self._relatives(graph, new, relative)
        self._update(graph, values, stamps)

    def _bias_priors(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: gtsam.FixedLagSmootherKeyTimestampMap,
        t: float,
    ) -> None:
        """The online biases' prior (module docstring), every key at its prior mean."""
        if self.prior is not None:
            add_bias_prior(graph, values, stamps, t, self.prior, self.bias_keys, self.offset_keys)

    def _ranges(
        self, graph: gtsam.NonlinearFactorGraph, keys: list[int], ranges: RangeTerms
    ) -> None:
        huber = gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K)
        rows = zip(
            ranges.index_a.tolist(),
            ranges.index_b.tolist(),
            ranges.distance.tolist(),
            ranges.sigma.tolist(),
            ranges.bias.tolist(),
            strict=True,
        )
        for a, b, d, s, j in rows:
            noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(1, s))
            if j >= 0:
                graph.add(
                    gtsam.CustomFactor(
                        noise, [keys[a], keys[b], self.bias_keys[j]], _biased_range(d)
                    )
                )
            else:
                graph.add(gtsam.RangeFactor2(keys[a], keys[b], d, noise))

    def _relatives(
        self, graph: gtsam.NonlinearFactorGraph, keys: list[int], relative: Relative | None
    ) -> None:
        """One Huber-robust between factor per measured ``p_target - p_observer``."""
        if relative is None:
            return
        huber = gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K)
        for a, b, v, c in zip(
            relative.observer.tolist(),
            relative.target.tolist(),
            relative.vector,
            relative.cov,
            strict=True,
        ):
            noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Gaussian.Covariance(c))
            graph.add(gtsam.BetweenFactorPoint2(keys[a], keys[b], np.asarray(v, float), noise))

    def _update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: gtsam.FixedLagSmootherKeyTimestampMap,
    ) -> None:
        self.smoother.update(graph, values, stamps)
        self.factors_added += graph.size()
        self._joint = None
        self._estimate = est = self.smoother.calculateEstimate()
        if self.record:
            self.graphs.append(graph)
            for key in list(est.keys()):  # a gtsam.Values, not a dict
                vector = gtsam.Symbol(key).chr() in (BIAS_CHR, OFFSET_CHR)
                self.values[key] = est.atVector(key) if vector else est.atPoint2(key)
        self.positions = np.array([est.atPoint2(key) for key in self.keys()], float).reshape(
            self.n, 2
        )
        self.biases = np.array([est.atVector(key)[0] for key in self.bias_keys], float)

    def _window_joint(self) -> FloatArray:
        """The joint covariance of the window's marginal on ``[x_ref, x_others..., biases...,
        offsets...]`` (the latest step's keys, 2 rows each, then 1 per bias and shared offset)
        at the estimate, once per update.

        The linearised window is eliminated with those keys last, so their marginal is the
        dense ``R^T R`` of one small Bayes net: four times cheaper than ``gtsam.Marginals``'
        joint over the same keys at 50 robots, and equal to it."""
        if self._joint is None:
            keys = self.keys()
            order = [
                keys[self.reference],
                *(keys[i] for i in self.others),
                *self.bias_keys,
                *self.offset_keys,
            ]
            linear = self.smoother.getFactors().linearize(self._estimate)
            r, _ = linear.marginalMultifrontalBayesNet(gtsam.Ordering(order)).matrix()
            r_inv = solve_triangular(r, np.eye(r.shape[0]))
            self._joint = r_inv @ r_inv.T
        return self._joint

    def covariances(self) -> FloatArray:
        """Covariance ``(N-1, 2, 2)`` of each robot's latest position relative to the
        reference's: ``S_kk + S_rr - S_kr - S_rk`` of the window's joint marginal."""
        k = self.others.size
        return _difference_covariances(self._window_joint()[: 2 * (k + 1), : 2 * (k + 1)], k)

    def bias_std(self) -> FloatArray:
        """Std of each online bias (the window's marginal), ``(B,)``."""
        tail = np.diag(self._window_joint())[2 * self.n : 2 * self.n + len(self.bias_keys)]
        return np.sqrt(np.maximum(tail, 0.0))

    def bias_joint(self) -> FloatArray:
        """The joint covariance of the online biases and then the shared offsets (the
        window's marginal) ``(B + L, B + L)``."""
        return self._window_joint()[2 * self.n :, 2 * self.n :]

    def offset_estimates(self) -> tuple[list[float], list[float]]:
        """Each shared offset's estimate and std (the window's marginal)."""
        if not self.offset_keys:
            return [], []
        est = self._estimate
        mean = [float(est.atVector(k)[0]) for k in self.offset_keys]
        tail = np.diag(self._window_joint())[2 * self.n + len(self.bias_keys) :]
        return mean, np.sqrt(np.maximum(tail, 0.0)).tolist()

    def batch(
        self, steps: list[int], covariances: bool = True
    ) -> tuple[FloatArray, FloatArray | None]:
        """The smoothed trajectory: every factor since the start optimised at once
        (Levenberg-Marquardt from the fixed-lag estimates), each robot's position relative to
        the reference at each of ``steps`` ``(S, N-1, 2)``, and with ``covariances`` their
        covariances ``(S, N-1, 2, 2)`` from the batch graph's joint marginals (else ``None``).
        Raises GTSAM's ``RuntimeError`` where the system is indeterminate."""
        graph, result = self._optimised()
        mean = np.empty((len(steps), self.others.size, 2))
        for j, step in enumerate(steps):
            pos = np.array([result.atPoint2(key) for key in self.keys(step)], float).reshape(
                self.n, 2
            )
            mean[j] = pos[self.others] - pos[self.reference]
        if not covariances:
            return mean, None
        marginals = gtsam.Marginals(graph, result)
        cov = np.empty((len(steps), self.others.size, 2, 2))
        for j, step in enumerate(steps):
            keys = self.keys(step)
            order = [keys[self.reference], *(keys[i] for i in self.others)]
            cov[j] = _difference_covariances(
                marginals.jointMarginalCovariance(order).fullMatrix(), self.others.size
            )
        return mean, cov

    def batch_joint(self, steps: list[int]) -> tuple[FloatArray, FloatArray]:
        """:meth:`batch`'s optimum as every key's absolute position at each of ``steps``
        ``(S, N, 2)`` and their joint covariance ``(S, 2N, 2N)`` (team order)."""
        graph, result = self._optimised()
        marginals = gtsam.Marginals(graph, result)
        pos = np.empty((len(steps), self.n, 2))
        joint = np.empty((len(steps), 2 * self.n, 2 * self.n))
        for j, step in enumerate(steps):
            keys = self.keys(step)
            pos[j] = np.array([result.atPoint2(key) for key in keys], float).reshape(self.n, 2)
            joint[j] = marginals.jointMarginalCovariance(keys).fullMatrix()
        return pos, joint

    def _optimised(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """Every factor since the start and their Levenberg-Marquardt optimum (from the
        fixed-lag estimates)."""
        graph = gtsam.NonlinearFactorGraph()
        for g in self.graphs:
            graph.push_back(g)
        initial = gtsam.Values()
        for key, value in self.values.items():
            initial.insert(key, np.asarray(value, float))  # a bias's Vector1 stays a Vector
        result = gtsam.LevenbergMarquardtOptimizer(
            graph, initial, gtsam.LevenbergMarquardtParams()
        ).optimize()
        return graph, result

    def point_joint(self) -> FloatArray:
        """The joint covariance ``(2N, 2N)`` of every key of the latest step (team order,
        absolute positions: the window's marginal)."""
        order = [self.reference, *self.others.tolist()]
        joint = self._window_joint()[: 2 * self.n, : 2 * self.n]
        rows = np.empty(2 * self.n, np.intp)
        for slot, i in enumerate(order):
            rows[2 * i : 2 * i + 2] = (2 * slot, 2 * slot + 1)
        return joint[np.ix_(rows, rows)]

    def cost(self) -> float:
        """The graph's error at the estimate (half the robust chi-square): compares hypotheses
        over the same measurements."""
        return float(self.smoother.getFactors().error(self._estimate))

    def size(self) -> int:
        """Factors the smoother holds now (marginalised ones replaced by their summary)."""
        graph = self.smoother.getFactors()
        return sum(1 for i in range(graph.size()) if graph.exists(i))


def _difference_covariances(joint: FloatArray, k: int) -> FloatArray:
    """From the joint covariance of ``[x_ref, x_1..x_k]`` (``(2k+2, 2k+2)``), each
    ``x_j - x_ref``'s: ``S_jj + S_rr - S_jr - S_rj`` ``(k, 2, 2)``, symmetrised."""
    blocks = joint.reshape(k + 1, 2, k + 1, 2).transpose(0, 2, 1, 3)
    j = np.arange(1, k + 1)
    out = blocks[j, j] + blocks[0, 0] - blocks[j, 0] - blocks[0, j]
    return 0.5 * (out + out.transpose(0, 2, 1))
