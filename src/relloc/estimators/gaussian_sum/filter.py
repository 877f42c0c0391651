"""A Gaussian-sum particle filter for self-calibration: headings, odometry scales, range biases.

Self-calibration adds, per robot, the rotation of its odometry frame relative to the
reference robot's (uniform on the circle a priori) and an odometry scale, and, per UWB pair,
a range bias. Sampling them as particle coordinates multiplies the dimension: five robots give
4 headings + 5 scales + 10 biases on top of 8 positions, and a uniform heading prior per robot
alone needs ``(360 / 10)^4 ~ 10^6`` particles to put one near the truth. Worse, the evidence
about a heading arrives a little at every step (odometry increments compared with range
changes); a particle that carries one sampled trajectory cannot integrate it, it can only be
selected, so brute force stays hopeless at any affordable count.

The derivation: docs/explanation/internals.md, section ``relloc.estimators.gaussian_sum.filter``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.special import log_ndtr

from relloc.filter.base import (
    ESS_THRESHOLD,
    REINJECT_FRACTION,
    FilterEstimate,
    WeightedFilter,
    renormalized,
)
from relloc.filter.calibration import (
    CalibrationLayout,
    CalibrationNoise,
    calibration_prior,
    circular_heading,
    rotation_jacobian,
    to_body_frame,
)
from relloc.filter.heading_split import split_headings
from relloc.filter.measurement import MeasurementModel, robust_gaussian
from relloc.filter.motion import OdometryMotion
from relloc.filter.resampling import mixture_moments
from relloc.filter.summary import Evidence, ModeSummary, summarize

__all__ = ["CalibrationLayout", "CalibrationNoise", "GaussianSumFilter"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


TRUNCATION_NEGLIGIBLE = 8.0
"""A scale interval whose ends lie this many standard deviations beyond a Gaussian's scale
leaves it unchanged (its mass outside is under 1e-15)."""


def truncated_normal(a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The standard normal truncated to ``[a, b]`` (elementwise, ``a < b``): the log of its
    mass, its mean and its variance, stable for intervals far in either tail (computed on the
    side of the origin where the interval lies is the smaller tail)."""
    flip = a + b > 0.0
    lo, hi = np.where(flip, -b, a), np.where(flip, -a, b)  # now lo + hi <= 0: the left tail
    log_hi, log_lo = log_ndtr(hi), log_ndtr(lo)
    log_z = log_hi + np.log1p(-np.exp(np.minimum(log_lo - log_hi, 0.0)))
    q_lo = np.exp(-0.5 * lo * lo - _LOG_SQRT_2PI - log_z)  # phi(lo) / Z
    q_hi = np.exp(-0.5 * hi * hi - _LOG_SQRT_2PI - log_z)
    mu = q_lo - q_hi
    lo_term = np.where(np.isfinite(lo), lo * q_lo, 0.0)
    hi_term = np.where(np.isfinite(hi), hi * q_hi, 0.0)
    var = np.maximum(1.0 + lo_term - hi_term - mu * mu, 1e-12)
    return log_z, np.where(flip, -mu, mu), var


class GaussianSumFilter(WeightedFilter):
    """``M`` weighted Gaussians over positions and calibration parameters (see module doc)."""

    layout: CalibrationLayout

    def __init__(
        self,
        layout: CalibrationLayout,
        n_particles: int,
        area: tuple[float, float, float, float],
        *,
        rng: np.random.Generator,
        noise: CalibrationNoise | None = None,
        bias_prior: tuple[FloatArray, FloatArray] | None = None,
        position_sigma: float = 0.2,
        motion: OdometryMotion | None = None,
        ess_threshold: float = ESS_THRESHOLD,
        reinject_fraction: float = REINJECT_FRACTION,
        heading_prior: dict[str, tuple[float, float]] | None = None,
        split_heading_std: float = 0.0,
    ) -> None:
        super().__init__(
            n_particles,
            area,
            rng=rng,
            resample="ess",
            ess_threshold=ess_threshold,
            reinject_fraction=reinject_fraction,
        )
        self.layout = layout
        self.noise = noise or CalibrationNoise()
        self.position_sigma = position_sigma
        self.motion = motion or OdometryMotion()
        """The odometry noise model (the sampled filter's): its per-robot variances and random
        walk are the prediction's process noise."""
        nb = len(layout.bias_pairs)
        if bias_prior is None:
            bias_prior = (np.zeros(nb), np.full(nb, 0.25**2))
        self.bias_prior_mean = np.asarray(bias_prior[0], float)
        self.bias_prior_var = np.asarray(bias_prior[1], float)
        if self.bias_prior_mean.shape != (nb,) or self.bias_prior_var.shape != (nb,):
            raise ValueError(f"bias_prior needs {nb} means and variances")
        self.heading_prior = heading_prior or {}
        self.split_heading_std = split_heading_std
        """Heading mode: split a Gaussian whose known heading's angular std exceeds this (rad;
        0: never) (:meth:`split_headings`)."""
        self.split_count = 0
        self.prior_mean, self.prior_cov = calibration_prior(
            layout, self.noise, self.heading_prior, self.bias_prior_mean, self.bias_prior_var
        )
        self._pending: list[tuple[FloatArray, FloatArray]] = []
        self.mean = np.zeros((n_particles, layout.width))
        self.cov = np.zeros((n_particles, layout.width, layout.width))
        self.magnitude_done = np.zeros((n_particles, layout.n_others), dtype=bool)
        self.magnitude_count = 0
        self.evidence = Evidence(len(layout.robots))
        """What was fused that can resolve the formation's orientation (for ``estimate``)."""
        self.covariance_floor = 0.0
        """Variance (m^2) added per axis to the published covariances: the error the spread
        of the hypotheses cannot show (:mod:`relloc.filter.summary`; set by the localizer)."""
        self.initialize(self.sample_positions(n_particles))

    @property
    def shared_heading(self) -> bool:
        """In heading mode the frame is the reference robot's odometry frame, not a compass."""
        return not self.layout.heading

    def counters(self) -> dict[str, int]:
        if not self.layout.heading:
            return {}
        out = {"scale_priors_applied": self.magnitude_count}
        if self.split_heading_std > 0.0:
            out["heading_splits"] = self.split_count
        return out

    # ---------------------------------------------------------------- covariance
    @property
    def cov(self) -> FloatArray:
        """``(M, D, D)`` covariances, with every range update so far applied."""
        if self._pending:
            self._flush()
        return self._cov

    @cov.setter
    def cov(self, value: FloatArray) -> None:
        self._pending.clear()
        self._cov = value

    def _flush(self) -> None:
        """Apply the pending rank-one updates ``P -= gain pht^T`` of the scalar updates since
        the covariance was last read, as one batched product (see :meth:`_scalar_update`)."""
        gains = np.stack([g for g, _ in self._pending], axis=2)  # (M, D, k)
        phts = np.stack([p for _, p in self._pending], axis=1)  # (M, k, D)
        self._pending.clear()
        self._cov -= gains @ phts

    # ---------------------------------------------------------------- prior
    def sample_positions(self, m: int) -> FloatArray:
        """``m`` relative formations uniform over the prior box, shape ``(m, 2(N-1))``."""
        return self.prior.sample(self.rng, m, self.layout.n_others)

    def initialize(self, positions: FloatArray) -> None:
        """Start every Gaussian at one formation hypothesis (``positions``: ``(M, 2(N-1))``),
        with isotropic position uncertainty ``position_sigma`` and the calibration prior."""
        self._set_prior_rows(np.arange(self.n), positions)
        self.logw = np.full(self.n, -math.log(self.n))

    def _set_prior_rows(self, rows: IntArray, positions: FloatArray) -> None:
        lay = self.layout
        self.mean[rows, : lay.dim] = positions
        self.mean[rows, lay.dim :] = self.prior_mean
        self.cov[rows] = 0.0
        idx = np.arange(lay.dim)
        self.cov[np.ix_(rows, idx, idx)] = np.eye(lay.dim) * self.position_sigma**2
        self.cov[rows, lay.dim :, lay.dim :] = self.prior_cov
        # a heading prior already holds |u| to its scale prior
        self.magnitude_done[rows] = np.array(
            [r in self.heading_prior for r in lay.others], dtype=bool
        )

    # ---------------------------------------------------------------- prediction
    def predict(self, disp: FloatArray, sigma: FloatArray, dt: float) -> None:
        """Move every Gaussian by the robots' odometry over one step.

        ``disp`` (N, 2): each robot's displacement (fixed scales already applied), in its own
        odometry frame in heading mode, else in the shared frame; ``sigma`` (N,): its standard
        deviation per axis.
        """
        self.evidence.moved(disp)
        lay, nz = self.layout, self.noise
        ref = lay.index(lay.reference)
        others = [lay.index(r) for r in lay.others]
        d_ref = disp[ref]
        width = lay.width
        g = np.zeros((width, width))
        shift = np.zeros(width)
        s_ref = lay.ref_scale_column
        for k, i in enumerate(others):
            rows = slice(2 * k, 2 * k + 2)
            if lay.heading:
                c0, _ = lay.u_columns(lay.reference)
                g[rows, c0 : c0 + 2] = -rotation_jacobian(d_ref)
            elif s_ref >= 0:
                g[rows, s_ref] = -d_ref
            else:
                shift[rows] = -d_ref
            if lay.heading:
                c0, _ = lay.u_columns(lay.robots[i])
                g[rows, c0 : c0 + 2] = rotation_jacobian(disp[i])
            elif lay.scale:
                g[rows, lay.scale_column(lay.robots[i])] = disp[i]
            else:
                shift[rows] += disp[i]
        # Process noise: each robot's own odometry noise and a random walk; the reference's
        # noise is common to every relative position.
        q = np.zeros((width, width))
        own = self.motion.own_variance(sigma, others, dt)
        for k in range(lay.n_others):
            q[2 * k, 2 * k] = q[2 * k + 1, 2 * k + 1] = own[k]
        if sigma[ref] > 0.0:
            for a in range(lay.n_others):
                for b in range(lay.n_others):
                    q[2 * a, 2 * b] += sigma[ref] ** 2
                    q[2 * a + 1, 2 * b + 1] += sigma[ref] ** 2
        if dt > 0.0:
            if lay.scale:
                for r in lay.robots:
                    c = lay.scale_column(r)
                    if c >= 0:
                        q[c, c] += nz.scale_walk**2 * dt
            for k in range(len(lay.bias_pairs)):
                c = lay.bias_start + k
                q[c, c] += nz.bias_walk**2 * dt
            if lay.colored_bias:
                idx = np.arange(lay.colored_start, lay.colored_end)
                q[idx, idx] += nz.colored_sigma**2 * (1.0 - math.exp(-2.0 * dt / nz.colored_time))
        rows_g = np.flatnonzero(np.any(g != 0.0, axis=1))
        if rows_g.size:
            cols_g = np.flatnonzero(np.any(g != 0.0, axis=0))
            gr = g[np.ix_(rows_g, cols_g)]  # (r, k): G is nonzero only there
            self.mean[:, rows_g] += self.mean[:, cols_g] @ gr.T
            # P' = (I + G) P (I + G)^T
            self.cov[:, rows_g, :] += np.einsum(
                "rk,mke->mre", gr, self.cov[:, cols_g, :]
            )  # (I+G) P
            self.cov[:, :, rows_g] += self.cov[:, :, cols_g] @ gr.T  # + (I+G) P G^T
        if lay.colored_bias and dt > 0.0:
            # first-order Gauss-Markov: c' = rho c + w, stationary variance colored_sigma^2
            # (its columns are outside G's rows and columns: the two steps commute)
            rho = math.exp(-dt / nz.colored_time)
            cs = slice(lay.colored_start, lay.colored_end)
            self.mean[:, cs] *= rho
            self.cov[:, cs, :] *= rho
            self.cov[:, :, cs] *= rho
        self.mean += shift
        self.cov += q
        if dt > 0.0:
            for robot in lay.rate_robots:
                self._turn_by_rate(robot, dt)
        if lay.heading and dt > 0.0:
            self._heading_walk(dt)
            if self.split_heading_std > 0.0:
                self.split_count += self.split_headings(self.split_heading_std)

    def _turn_by_rate(self, robot: str, dt: float) -> None:
        """Turn ``robot``'s ``u`` by its drift rate over ``dt`` (layout ``rates``):
        ``u' = R(w dt) u``, linearised per Gaussian (``du'/du = R(w dt)``, ``du'/dw = dt J u'``,
        ``J`` the quarter turn), ``P' = F P F^T``."""
        lay = self.layout
        c0, c1 = lay.u_columns(robot)
        rc = lay.rate_column(robot)
        uc = np.array([c0, c1])
        angle = self.mean[:, rc] * dt
        c, s = np.cos(angle), np.sin(angle)
        rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (M, 2, 2)
        u = np.einsum("mab,mb->ma", rot, self.mean[:, c0 : c1 + 1])
        self.mean[:, c0 : c1 + 1] = u
        du_dw = dt * np.stack([-u[:, 1], u[:, 0]], -1)  # (M, 2)
        cov = self.cov
        rows = (
            np.einsum("mab,mbd->mad", rot, cov[:, uc, :]) + du_dw[:, :, None] * cov[:, None, rc, :]
        )
        cov[:, uc, :] = rows
        cols = (
            np.einsum("mdb,mab->mda", cov[:, :, uc], rot) + cov[:, :, rc, None] * du_dw[:, None, :]
        )
        cov[:, :, uc] = cols
        self.cov = cov

    def _heading_walk(self, dt: float) -> None:
        """Random walk of each ``u``: ``heading_walk`` along the circle (turning ``u``, scaled by
        its length) and ``scale_walk`` along its length, per particle. A ``u`` still unknown
        (short mean) gets the isotropic turn noise of a unit vector."""
        nz = self.noise
        for robot in self.layout.robots:
            c0, c1 = self.layout.u_columns(robot)
            mu = self.mean[:, c0 : c1 + 1]
            norm = np.sqrt(np.sum(mu * mu, axis=1))
            r = np.where(norm[:, None] > 1e-9, mu / np.maximum(norm, 1e-9)[:, None], [1.0, 0.0])
            t = np.stack([-r[:, 1], r[:, 0]], axis=1)
            known = np.clip(norm, 0.0, 1.0)  # |u| once known, ~1; 0 while unknown
            walk = nz.reference_heading_walk if robot == self.layout.reference else nz.heading_walk
            q_t = walk**2 * dt * np.maximum(norm, 1.0) ** 2
            q_r = (nz.scale_walk**2 * dt if self.layout.scale else 0.0) * known + q_t * (
                1.0 - known
            )
            block = q_t[:, None, None] * t[:, :, None] * t[:, None, :]
            block += q_r[:, None, None] * r[:, :, None] * r[:, None, :]
            self.cov[:, c0 : c1 + 1, c0 : c1 + 1] += block

    # ---------------------------------------------------------------- splitting
    def split_headings(self, max_std: float) -> int:
        """Split every Gaussian whose widest known heading (angular std of ``u``: tangential std
        over ``|u|``) exceeds ``max_std`` (rad) into three along that heading, then resample the
        enlarged mixture back to ``M`` (systematic; equal weights). Returns how many Gaussians
        were split (:mod:`relloc.filter.heading_split`)."""
        count, split = split_headings(
            self.layout, self.mean, self.cov, self.logw, self.magnitude_done, max_std, self.rng
        )
        if split is not None:
            self.mean, self.cov, self.logw, self.magnitude_done = split
        return count

    # ---------------------------------------------------------------- updates
    def update(self, models: Sequence[MeasurementModel]) -> bool:
        """Fuse every scalar row of every model, each linearised at the means as updated by
        the rows before it; then (heading mode) the ``|u|`` pseudo-measurements that have
        become due, and normalise. False (weights kept) if no Gaussian has any support."""
        before = self.logw
        self.evidence.fused(models)
        u_before = self._u_means() if self.layout.heading else None
        for model in models:
            for k in range(model.rows):
                row = model.row(k, self.mean)
                self._scalar_update(
                    row.columns, row.jacobian, row.residual, row.variance, row.density
                )
        if u_before is not None:
            self._turn_headings(u_before)
        if self.layout.heading:
            self.magnitude_count += self.apply_magnitude_priors(np.ones(self.layout.n_others))
        self.constrain_scales()
        logw = renormalized(self.logw)
        ok = logw is not None
        self.logw = logw if logw is not None else before
        self.cov = 0.5 * (self.cov + self.cov.transpose(0, 2, 1))  # symmetric against round-off
        return ok

    def _u_means(self) -> FloatArray:
        """Every robot's ``u`` per Gaussian, ``(M, N, 2)`` (heading mode)."""
        cols = [c for r in self.layout.robots for c in self.layout.u_columns(r)]
        return self.mean[:, cols].reshape(self.n, len(self.layout.robots), 2).copy()

    def _turn_headings(self, u_before: FloatArray) -> None:
        """Apply the update's correction of each known ``u`` as a turn and a change of length
        (polar), not as a vector sum.

        The Kalman update adds ``du`` to ``u``; its component along ``u`` is evidence about
        the scale, its component across ``u`` about the angle. Added as a vector, a turn by
        ``delta`` also lengthens ``u`` by ``|u| (sqrt(1 + delta^2) - 1)``, whatever its sign:
        every heading correction ratchets the scale up, and with sparse sightings after long
        gaps (wide headings, large turns) the scale runs out of its physical interval. Here the
        across component turns ``u`` by ``delta = du_t / |u|`` (its covariance turned with it)
        and only the along component changes its length. A ``u`` whose angle is still unknown
        (the Gaussian's ``|u|`` pseudo-measurement not yet applied; the reference's is always
        known) keeps the linear update: its prior is a Gaussian in ``u`` itself."""
        lay = self.layout
        mean, cov = self.mean, self.cov
        for i, robot in enumerate(lay.robots):
            known = (
                np.ones(self.n, dtype=bool)
                if robot == lay.reference
                else self.magnitude_done[:, lay.others.index(robot)]
            )
            u0 = u_before[:, i]
            norm = np.sqrt(np.sum(u0 * u0, axis=1))
            known &= norm > 1e-6
            if not np.any(known):
                continue
            c0, c1 = lay.u_columns(robot)
            rows = np.flatnonzero(known)
            u0, norm = u0[rows], norm[rows]
            r = u0 / norm[:, None]
            t = np.stack([-r[:, 1], r[:, 0]], axis=1)
            du = mean[rows, c0 : c1 + 1] - u0
            length = norm + np.einsum("ma,ma->m", du, r)
            delta = np.einsum("ma,ma->m", du, t) / norm
            c, s = np.cos(delta), np.sin(delta)
            mean[rows, c0] = length * (c * r[:, 0] + s * t[:, 0])
            mean[rows, c1] = length * (c * r[:, 1] + s * t[:, 1])
            rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # R(delta)
            uc = np.array([c0, c1])
            cov[rows[:, None], uc[None, :], :] = np.einsum(
                "mab,mbd->mad", rot, cov[rows[:, None], uc[None, :], :]
            )
            cov[rows[:, None], :, uc[None, :]] = np.einsum(
                "mab,mbd->mad", rot, cov[rows[:, None], :, uc[None, :]]
            )
        self.cov = cov

    def constrain_scales(self) -> None:
        """Hold every Gaussian's odometry scale inside its physical interval
        (:attr:`CalibrationNoise.scale_bounds`): the prior of a scale is zero outside it.

        Per Gaussian and robot whose scale is known (``|u|`` once its angle is, or the scale
        column), the scale is ``h . x`` (``h`` along ``u``, or the column); the constraint
        ``lo <= h . x <= hi`` is a measurement, so the Gaussian's weight is multiplied by its
        mass inside the interval and the Gaussian is conditioned on it, moment-matched: its
        scale takes the truncated normal's mean and variance, every correlated state moves
        with it (the truncation of Simon and Simon, "Kalman filtering with inequality
        constraints"). A hypothesis that needs an impossible scale loses its weight rather
        than publishing the scale; no mixture mean can leave the interval."""
        lay = self.layout
        if not lay.scale:
            return
        lo, hi = self.noise.scale_bounds
        mean, cov = self.mean, self.cov
        for robot in lay.robots:
            if lay.heading:
                c0, c1 = lay.u_columns(robot)
                cols = np.array([c0, c1])
                u = mean[:, c0 : c1 + 1]
                m = np.sqrt(np.sum(u * u, axis=1))
                known = m > 1e-6
                if robot != lay.reference:
                    known &= self.magnitude_done[:, lay.others.index(robot)]
                h = u / np.maximum(m, 1e-12)[:, None]
            else:
                c = lay.scale_column(robot)
                if c < 0:
                    continue
                cols = np.array([c])
                m = mean[:, c]
                known = np.ones(self.n, dtype=bool)
                h = np.ones((self.n, 1))
            pht = np.einsum("mdc,mc->md", cov[:, :, cols], h)
            v = np.maximum(np.einsum("mc,mc->m", pht[:, cols], h), 1e-18)
            sd = np.sqrt(v)
            a, b = (lo - m) / sd, (hi - m) / sd
            rows = np.flatnonzero(
                known & ((a > -TRUNCATION_NEGLIGIBLE) | (b < TRUNCATION_NEGLIGIBLE))
            )
            if not rows.size:
                continue
            log_z, shift, ratio = truncated_normal(a[rows], b[rows])
            p = pht[rows]
            mean[rows] += p * (sd[rows] * shift / v[rows])[:, None]
            cov[rows] -= p[:, :, None] * p[:, None, :] * ((1.0 - ratio) / v[rows])[:, None, None]
            self.logw[rows] += log_z
        self.cov = cov

    def apply_magnitude_priors(self, nominal: FloatArray) -> int:
        """Heading mode: apply the prior on ``|u|`` (``nominal[k]`` +- the scale sigma) once,
        to every particle whose angle of ``u`` is now determined. Returns how many."""
        lay, nz = self.layout, self.noise
        if not lay.heading:
            return 0
        sigma = nz.scale_prior_sigma if lay.scale else nz.scale_fixed_sigma
        applied = 0
        for k, robot in enumerate(lay.others):
            c0, c1 = lay.u_columns(robot)
            mu = self.mean[:, c0 : c1 + 1]
            norm = np.sqrt(np.sum(mu * mu, axis=1))
            block = self.cov[:, c0 : c1 + 1, c0 : c1 + 1]
            lam = 0.5 * (block[:, 0, 0] + block[:, 1, 1]) + np.sqrt(
                0.25 * (block[:, 0, 0] - block[:, 1, 1]) ** 2 + block[:, 0, 1] ** 2
            )
            ready = ~self.magnitude_done[:, k] & (np.sqrt(lam) < nz.magnitude_gate * norm)
            if not np.any(ready):
                continue
            rows = np.flatnonzero(ready)
            h = mu[rows] / norm[rows, None]
            self._scalar_update(
                np.array([c0, c1]),
                h,
                nominal[k] - norm[rows],
                sigma**2,
                lambda r, s: robust_gaussian(r, s, 0.0, 1.0),
                rows=rows,
            )
            self.magnitude_done[rows, k] = True
            applied += rows.size
        return applied

    def _scalar_update(
        self,
        cols: IntArray,
        h: FloatArray,
        residual: FloatArray,
        r_var: float,
        density: Callable[[FloatArray, FloatArray], tuple[FloatArray, FloatArray]],
        rows: IntArray | None = None,
    ) -> FloatArray:
        """Robust scalar EKF update of ``rows`` (default all) with measurement Jacobian ``h``
        (``(m, len(cols))``, nonzero only in ``cols``), innovation ``residual`` and noise
        variance ``r_var``. ``density(residual, s)`` gives the log predictive density of the
        innovation (predictive variance ``s``) and the inlier probability that scales the gain.

        Updating all rows, the covariance update ``P -= gain pht^T`` is deferred: the next
        update needs only ``P h``, which the pending updates give at ``O(M D)`` each
        (``P h = P0 h - sum_i gain_i (pht_i . h)``), and the whole batch of ranges is applied
        at once when the covariance is next read. Exactly the sequential updates, at a fraction
        of the memory traffic of one ``(M, D, D)`` pass per range."""
        if rows is None:
            mean = self.mean
            pht = np.einsum("mdc,mc->md", self._cov[:, :, cols], h)  # P0 h, (m, D)
            for g_i, p_i in self._pending:
                pht -= g_i * np.einsum("mc,mc->m", p_i[:, cols], h)[:, None]
        else:
            mean, cov = self.mean[rows], self.cov[rows]
            pht = np.einsum("mdc,mc->md", cov[:, :, cols], h)  # (m, D)
        s = np.einsum("mc,mc->m", pht[:, cols], h) + r_var
        s = np.maximum(s, 1e-12)
        ll, inlier = density(residual, s)
        gain = pht * (inlier / s)[:, None]
        mean += gain * residual[:, None]
        if rows is None:
            self._pending.append((gain, pht))
            self.logw = self.logw + ll
        else:
            cov -= gain[:, :, None] * pht[:, None, :]
            self.mean[rows], self.cov[rows] = mean, cov
            self.logw[rows] += ll
        return ll

    # ---------------------------------------------------------------- resampling
    def _select(self, idx: IntArray) -> None:
        self.mean = self.mean[idx]
        self.cov = self.cov[idx]
        self.magnitude_done = self.magnitude_done[idx]

    def _reinject(self, slots: IntArray, positions: FloatArray) -> None:
        self._set_prior_rows(slots, positions)

    # ---------------------------------------------------------------- estimates
    def estimate(self) -> FilterEstimate:
        """The positions' honest summary (:func:`relloc.filter.summary.summarize` over the
        Gaussians, their own covariances included), and the mixture moments of every
        estimated heading, bias and scale."""
        lay = self.layout
        k = lay.n_others
        rel = self.mean[:, : 2 * k].reshape(self.n, k, 2)
        idx = 2 * np.arange(k)
        covs = self.cov[
            :,
            idx[:, None, None] + np.arange(2)[None, :, None],
            idx[:, None, None] + np.arange(2)[None, None, :],
        ]
        summary = self._summary(rel, covs)
        headings = {robot: self.heading(robot) for robot in lay.robots} if lay.heading else {}
        biases = {pair: self.bias(pair) for pair in lay.bias_pairs}
        scales = {robot: self.scale(robot) for robot in lay.robots} if lay.scale else {}
        return FilterEstimate(
            summary.mean, summary.cov, self.ess(), headings, biases, scales, summary
        )

    def _summary(self, rel: FloatArray, covs: FloatArray) -> ModeSummary:
        """The mixture's honest summary of relative positions ``rel`` with covariances
        ``covs`` (:func:`relloc.filter.summary.summarize`), in whichever frame they are."""
        return summarize(
            rel,
            self.weights(),
            covs,
            can_resolve=self.evidence.can_resolve,
            floor=self.covariance_floor,
        )

    def body_estimate(self, reference_yaw: float) -> FilterEstimate | None:
        """:meth:`estimate` with the positions in the reference robot's body frame
        (:func:`relloc.filter.calibration.to_body_frame`; ``reference_yaw`` its odometry yaw),
        and each heading as the turn from a robot's odometry frame to that body frame (what its
        odometry yaw adds to give its yaw there). ``None`` without estimated headings: the
        frame is then the compass's, which the measurements observe."""
        lay = self.layout
        if not lay.heading:
            return None
        rel, covs = to_body_frame(
            self.mean, self.cov, lay.n_others, lay.u_columns(lay.reference), reference_yaw
        )
        summary = self._summary(rel, covs)
        ref_mean, ref_std = self.heading(lay.reference)
        headings = {}
        for robot in lay.robots:
            mean, std = self.heading(robot)
            turn = math.remainder(mean - ref_mean - reference_yaw, math.tau)
            headings[robot] = (turn, 0.0 if robot == lay.reference else math.hypot(std, ref_std))
        biases = {pair: self.bias(pair) for pair in lay.bias_pairs}
        scales = {robot: self.scale(robot) for robot in lay.robots} if lay.scale else {}
        return FilterEstimate(
            summary.mean, summary.cov, self.ess(), headings, biases, scales, summary
        )

    def weights(self) -> FloatArray:
        """Normalised weights (the log-weights are normalised by :meth:`update`; weights set
        from outside may not be)."""
        top = np.max(self.logw)
        if not np.isfinite(top):
            return np.full(self.n, 1.0 / self.n)
        w = np.exp(self.logw - top)
        return w / np.sum(w)

    def heading(self, robot: str) -> tuple[float, float]:
        """Circular mean and circular standard deviation (rad) of ``robot``'s relative heading
        (:func:`relloc.filter.calibration.circular_heading`)."""
        c0, c1 = self.layout.u_columns(robot)
        return circular_heading(
            self.mean[:, c0 : c1 + 1], self.cov[:, c0 : c1 + 1, c0 : c1 + 1], self.weights()
        )

    def scale(self, robot: str) -> tuple[float, float]:
        """Mean and std of ``robot``'s odometry scale (``|u|`` in heading mode)."""
        lay = self.layout
        w = self.weights()
        c = lay.scale_column(robot)
        if c >= 0:
            mu, var = self.mean[:, c], self.cov[:, c, c]
        elif lay.heading:
            c0, c1 = lay.u_columns(robot)
            u = self.mean[:, c0 : c1 + 1]
            mu = np.sqrt(np.sum(u * u, axis=1))
            r = u / np.maximum(mu, 1e-12)[:, None]
            var = np.einsum("ma,mab,mb->m", r, self.cov[:, c0 : c1 + 1, c0 : c1 + 1], r)
            if robot != lay.reference:
                # where the angle of u is still unknown, |u| says nothing yet: the prior stands
                prior = ~self.magnitude_done[:, lay.others.index(robot)]
                mu = np.where(prior, 1.0, mu)
                var = np.where(prior, self.noise.scale_prior_sigma**2, var)
        else:
            return math.nan, math.nan
        return mixture_moments(w, mu, var)

    def bias(self, pair: str) -> tuple[float, float]:
        """Mean and std of ``pair``'s online range bias."""
        c = self.layout.bias_column(pair)
        return mixture_moments(self.weights(), self.mean[:, c], self.cov[:, c, c])
