"""A Gaussian-sum filter over a large team's formation, with a sparse update over the range graph.

The derivation: docs/explanation/internals.md, section ``relloc.estimators.range_graph.filter``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from relloc import geometry
from relloc.filter.base import FilterEstimate, WeightedFilter, renormalized
from relloc.filter.measurement import MeasurementModel
from relloc.filter.motion import OdometryMotion
from relloc.filter.ranges import RangeBatch, range_mixture
from relloc.filter.resampling import log_normalize
from relloc.filter.state import StateLayout
from relloc.filter.summary import ORIENTATION_MAX_STD, Evidence, summarize
from relloc.localizers.priors import with_rotation_floor

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

MIN_INLIER = 1e-3
"""Floor of a range's inlier probability: its noise is inflated at most ``1 / MIN_INLIER``."""
_LOG_2PI = math.log(2.0 * math.pi)


class RangeGraphFilter(WeightedFilter):
    """Gaussian sum over the relative positions of a team, ranges fused in one sparse
    information-form update (module docstring)."""

    layout: StateLayout

    def __init__(
        self,
        layout: StateLayout,
        area: tuple[float, float, float, float],
        *,
        rng: np.random.Generator,
        motion: OdometryMotion | None = None,
        rotation_noise: float = 0.0,
        prune_weight: float = 1e-4,
        merge_distance: float = 0.05,
        reinject_sigma: float = 1.5,
        rotation_floor: float = 0.0,
    ) -> None:
        super().__init__(1, area, rng=rng, resample="every_step", reinject_fraction=0.0)
        self.layout = layout
        self.motion = motion or OdometryMotion()
        self.rotation_noise = rotation_noise
        self.prune_weight = prune_weight
        self.merge_distance = merge_distance
        self.reinject_sigma = reinject_sigma
        k = layout.n_others
        self.mean = np.zeros((1, 2 * k))
        self.cov = np.eye(2 * k)[None] * float(np.mean(self.half_extent**2) / 3.0)
        self.evidence = Evidence(len(layout.robots))
        self.covariance_floor = 0.0
        """Variance (m^2) added per axis to the published covariances (:mod:`relloc.filter.summary`)."""
        self.rotation_floor = rotation_floor
        """Std (rad) of a rotation of the whole formation added to the published covariances
        (module docstring, "What the covariance cannot show")."""
        self._others = np.array([layout.index(r) for r in layout.others], dtype=np.intp)
        self._reference = layout.index(layout.reference)
        self._slot = np.array([layout.slot(r) for r in layout.robots], dtype=np.intp)
        self.pruned = 0
        self.merged = 0

    # ---------------------------------------------------------------- start
    def initialize(
        self, formations: FloatArray, cov: FloatArray, logw: FloatArray | None = None
    ) -> None:
        """Start one Gaussian per formation (``(M, N-1, 2)`` or ``(M, 2(N-1))``) with
        covariances ``cov`` ``(M, D, D)`` and log-weights ``logw`` (default equal); the motion
        evidence starts again."""
        m = formations.shape[0]
        self.mean = np.asarray(formations, float).reshape(m, -1).copy()
        self.cov = np.asarray(cov, float).copy()
        self.n = m
        self.logw = (
            np.full(m, -math.log(m)) if logw is None else log_normalize(np.asarray(logw, float))
        )
        self.evidence.reset()

    # ---------------------------------------------------------------- cycle
    def predict(self, disp: FloatArray, sigma: FloatArray, dt: float) -> None:
        """Means by each robot's displacement less the reference's; covariances by the odometry
        noise (own and common) and the formation's random turn."""
        self.evidence.moved(disp)
        k = self.layout.n_others
        move = np.nan_to_num(disp[self._others] - disp[self._reference])
        self.mean += move.reshape(1, -1)
        own = self.motion.own_variance(sigma, self._others, dt)
        idx = np.arange(2 * k)
        self.cov[:, idx, idx] += np.repeat(own, 2)[None, :]
        common = float(sigma[self._reference]) ** 2
        if common > 0.0:
            block = np.kron(np.ones((k, k)), np.eye(2)) * common
            self.cov += block[None]
        if self.rotation_noise > 0.0 and dt > 0.0:
            jac = self._tangent()
            self.cov += self.rotation_noise**2 * dt * jac[:, :, None] * jac[:, None, :]

    def update(self, models: Sequence[MeasurementModel]) -> bool:
        """Fuse every model (ranges by the sparse update, others by their linear rows) and
        normalise the log-weights; False (weights kept) if no hypothesis has any support."""
        if not models:
            return True
        before = self.logw.copy()
        self.evidence.fused(models)
        for model in models:
            if isinstance(model, RangeBatch):
                self._range_update(model)
            else:
                self._row_update(model)
        logw = renormalized(self.logw)
        self.logw = before if logw is None else logw
        return logw is not None

    def _positions(self) -> FloatArray:
        """Every robot's relative position ``(M, N, 2)`` (the reference's row zero)."""
        m = self.mean.shape[0]
        out = np.zeros((m, len(self.layout.robots), 2))
        out[:, self._others] = self.mean.reshape(m, -1, 2)
        return out

    def _range_update(self, model: RangeBatch) -> None:
        """One information-form EKF update with all of ``model``'s ranges (module docstring)."""
        if model.bias_columns is not None or model.state_columns:
            raise ValueError("the range-graph filter has no online bias state")
        m, d = self.mean.shape
        k = d // 2
        sa, sb = self._slot[model.index_a], self._slot[model.index_b]
        pos = self._positions()
        dist, e = geometry.direction(pos[:, model.index_a] - pos[:, model.index_b])  # (M, K, 2)
        r = (model.distance - model.bias)[None, :] - dist  # (M, K)
        has_a, has_b = sa >= 0, sb >= 0
        both = has_a & has_b
        ca, cb = np.maximum(sa, 0), np.maximum(sb, 0)
        blocks = self.cov.reshape(m, k, 2, k, 2).transpose(0, 1, 3, 2, 4)  # (M, k, k, 2, 2) view
        blk = (
            blocks[:, ca, ca] * has_a[None, :, None, None]
            + blocks[:, cb, cb] * has_b[None, :, None, None]
        )
        cross = blocks[:, ca, cb] * both[None, :, None, None]
        blk -= cross + cross.transpose(0, 1, 3, 2)
        hph = np.einsum("mki,mkij,mkj->mk", e, blk, e)
        var = model.sigma[None, :] ** 2
        s = var + np.maximum(hph, 0.0)
        los, total = range_mixture(
            r,
            np.sqrt(s),
            model.outlier_fraction,
            model.max_range,
            model.nlos_fraction,
            model.nlos_sigma,
        )
        inlier = np.maximum(los / total, MIN_INLIER)
        w = inlier / var  # (M, K)

        # Lambda = H^T W H: a block graph Laplacian over the non-reference robots.
        outer = w[:, :, None, None] * e[:, :, :, None] * e[:, :, None, :]  # (M, K, 2, 2)
        inc = np.zeros((k, len(sa)))
        inc[sa[has_a], np.flatnonzero(has_a)] = 1.0
        inc[sb[has_b], np.flatnonzero(has_b)] += 1.0
        lam = np.zeros((m, k, k, 2, 2))
        diag = np.einsum("ok,mkij->moij", inc, outer)
        ar = np.arange(k)
        lam[:, ar, ar] = diag
        kb = np.flatnonzero(both)
        lam[:, sa[kb], sb[kb]] -= outer[:, kb]
        lam[:, sb[kb], sa[kb]] -= outer[:, kb].transpose(0, 1, 3, 2)
        lam = lam.transpose(0, 1, 3, 2, 4).reshape(m, d, d)  # type: ignore[assignment]
        # g = H^T W r: a signed incidence sum.
        signed = np.zeros((k, len(sa)))
        signed[sa[has_a], np.flatnonzero(has_a)] = 1.0
        signed[sb[has_b], np.flatnonzero(has_b)] -= 1.0
        g = np.einsum("ok,mki->moi", signed, (w * r)[:, :, None] * e).reshape(m, d)

        a = np.eye(d)[None] + self.cov @ lam
        cov = np.linalg.solve(a, self.cov)
        cov = 0.5 * (cov + cov.transpose(0, 2, 1))
        step = np.einsum("mde,me->md", cov, g)
        _, logdet = np.linalg.slogdet(a)
        maha = np.sum(w * r * r, axis=1) - np.einsum("md,md->m", g, step)
        norm = np.sum(np.log(var / inlier), axis=1) + r.shape[1] * _LOG_2PI
        self.logw = self.logw - 0.5 * (maha + logdet + norm)
        self.mean += step
        self.cov = cov

    def _row_update(self, model: MeasurementModel) -> None:
        """Scalar robust Kalman steps, one per linear row of ``model``."""
        for k in range(model.rows):
            row = model.row(k, self.mean)
            cols, h = row.columns, row.jacobian
            ph = np.einsum("mdc,mc->md", self.cov[:, :, cols], h)
            s = np.maximum(np.einsum("mc,mc->m", ph[:, cols], h) + row.variance, 1e-12)
            ll, inlier = row.density(row.residual, s)
            gain = ph * (inlier / s)[:, None]
            self.mean += gain * row.residual[:, None]
            self.cov -= gain[:, :, None] * ph[:, None, :]
            self.logw = self.logw + ll
        self.cov = 0.5 * (self.cov + self.cov.transpose(0, 2, 1))

    # ---------------------------------------------------------------- estimate
    def _tangent(self) -> FloatArray:
        """``d formation / d theta`` of every mean: each robot's ``(-y, x)``, ``(M, D)``."""
        m = self.mean.shape[0]
        rel = self.mean.reshape(m, -1, 2)
        return np.stack([-rel[:, :, 1], rel[:, :, 0]], axis=-1).reshape(m, -1)

    def rotation_std(self) -> FloatArray:
        """Each hypothesis's own std (rad) of the formation's rotation about the reference."""
        jac = self._tangent()
        norm2 = np.maximum(np.einsum("md,md->m", jac, jac), 1e-12)
        return np.sqrt(np.maximum(np.einsum("md,mde,me->m", jac, self.cov, jac), 0.0)) / norm2

    def weights(self) -> FloatArray:
        w = np.exp(self.logw - np.max(self.logw))
        return w / np.sum(w)

    def estimate(self) -> FilterEstimate:
        """The mixture's honest summary (module docstring)."""
        m, d = self.mean.shape
        k = d // 2
        w = self.weights()
        idx = 2 * np.arange(k)
        covs = self.cov[
            :,
            idx[:, None, None] + np.arange(2)[None, :, None],
            idx[:, None, None] + np.arange(2)[None, None, :],
        ]
        summary = summarize(
            self.mean.reshape(m, k, 2),
            w,
            covs,
            can_resolve=self.evidence.can_resolve,
            floor=self.covariance_floor,
        )
        if summary.orientation_observable:
            members = summary.members
            own = float(
                np.sum(w[members] * self.rotation_std()[members])
                / max(float(np.sum(w[members])), 1e-300)
            )
            if own >= ORIENTATION_MAX_STD:
                summary = replace(summary, orientation_observable=False)
        if self.rotation_floor > 0.0 and summary.orientation_observable:
            cov = with_rotation_floor(summary.mean, summary.cov, self.rotation_floor)
            summary = replace(summary, cov=cov)
        return FilterEstimate(
            summary.mean, summary.cov, float(1.0 / np.sum(w * w)), summary=summary
        )

    # ---------------------------------------------------------------- hypotheses
    def maybe_resample(self) -> bool:
        """Prune and merge hypotheses (module docstring); never resamples (False)."""
        self.resample()
        return False

    def resample(self) -> None:
        """Drop hypotheses under ``prune_weight`` and merge those within ``merge_distance``.
        Nothing is dropped before the fused motion could have told the orientations apart
        (:class:`relloc.filter.summary.Evidence`): the first updates' weights rank the
        hypotheses by how their transients settle, not by the orientation."""
        if not self.evidence.can_resolve:
            return
        w = self.weights()
        keep = np.flatnonzero(w >= min(self.prune_weight, float(w.max())))
        if keep.size < self.n:
            self.pruned += self.n - keep.size
            self._select(keep)
            self.logw = log_normalize(self.logw)
        if self.n > 1:
            self._merge()

    def _merge(self) -> None:
        m = self.n
        w = self.weights()
        diff = self.mean[:, None, :] - self.mean[None, :, :]
        rms = np.sqrt(np.mean(diff * diff, axis=2) * 2.0)  # per robot: x and y together
        close = rms < self.merge_distance
        if not np.any(close & ~np.eye(m, dtype=bool)):
            return
        group = np.full(m, -1, dtype=np.intp)
        leaders: list[int] = []
        for i in np.argsort(-w):  # a loop over hypotheses (tens at most), not particles
            if group[i] >= 0:
                continue
            free = close[i] & (group < 0)
            group[free] = len(leaders)
            leaders.append(int(i))
        g = len(leaders)
        onehot = np.zeros((g, m))
        onehot[group, np.arange(m)] = w
        wg = onehot.sum(axis=1)
        resp = onehot / wg[:, None]
        mean = resp @ self.mean
        dev = self.mean[None, :, :] - mean[:, None, :]  # (g, m, D)
        cov = np.einsum("gm,mde->gde", resp, self.cov) + np.einsum(
            "gm,gmd,gme->gde", resp, dev, dev
        )
        self.merged += m - g
        self.mean, self.cov, self.n = mean, cov, g
        self.logw = np.log(wg)

    def _select(self, idx: IntArray) -> None:
        self.mean = self.mean[idx]
        self.cov = self.cov[idx]
        self.n = len(idx)
        self.logw = self.logw[idx]

    def _reinject(self, slots: IntArray, positions: FloatArray) -> None:
        self.mean[slots] = positions
        self.cov[slots] = np.eye(self.mean.shape[1]) * self.reinject_sigma**2

    def counters(self) -> dict[str, int]:
        return {
            "hypotheses": self.n,
            "hypotheses_pruned": self.pruned,
            "hypotheses_merged": self.merged,
        }
