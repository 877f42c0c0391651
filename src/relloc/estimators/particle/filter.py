"""The particle filter over relative positions: NumPy and a few compiled passes, no I/O, no
knowledge of sensors.

One step (predict, update by ranges, estimate, resample) runs as a handful of compiled passes
over the particle rows (:func:`relloc.filter.motion.OdometryMotion.propagate`,
:meth:`relloc.filter.ranges.RangeBatch.add_log_likelihood`,
:func:`relloc.filter.resampling.renormalize_into`,
:func:`relloc.filter.summary.summarize_particles`,
:func:`relloc.filter.resampling.systematic_take`): a NumPy call per operation cost more than
the arithmetic at a few hundred particles, and a pass over memory per operation at tens of
thousands. Other measurement models, online biases and an adaptive count take the NumPy path.

The derivation: docs/explanation/internals.md, section ``relloc.estimators.particle.filter``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from relloc.filter import compiled
from relloc.filter.adaptive import KldSampling
from relloc.filter.annealing import MCMC_STEPS, StartContext, annealed_start, orient_by
from relloc.filter.base import (
    ESS_THRESHOLD,
    REINJECT_FRACTION,
    FilterEstimate,
    WeightedFilter,
    renormalized,
)
from relloc.filter.measurement import MeasurementModel, stacked
from relloc.filter.motion import OdometryMotion
from relloc.filter.ranges import RangeBatch
from relloc.filter.resampling import (
    ess,
    log_normalize,
    mixture_moments,
    renormalize_into,
    systematic_resample,
    systematic_take,
)
from relloc.filter.state import StateLayout
from relloc.filter.summary import Evidence, ModeSummary, summarize, summarize_particles

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
_BLOCK = 4096
"""Particles per block when evaluating likelihoods (see ``ParticleFilter.log_likelihood``)."""

ROTATION_KERNEL_MAX_SPREAD = 0.25
"""The orientation kernel acts only while the orientations form one mode with a robust standard
deviation below this (rad), never while rotations or mirror images compete."""

LogLikelihood = Callable[[FloatArray, FloatArray], FloatArray]
"""Maps relative positions (coordinate planes ``(2, N, M)``) and the particle rows ``(M, D)``
to log-likelihoods ``(M,)``."""


class ParticleFilter(WeightedFilter):
    """Particle filter for ``N`` robots' positions relative to a reference robot."""

    layout: StateLayout

    def __init__(
        self,
        layout: StateLayout,
        n_particles: int,
        area: tuple[float, float, float, float],
        *,
        rng: np.random.Generator,
        motion: OdometryMotion | None = None,
        resample: str = "ess",
        ess_threshold: float = ESS_THRESHOLD,
        reinject_fraction: float = REINJECT_FRACTION,
        extra_prior: FloatArray | None = None,
        extra_sampler: Callable[[np.random.Generator, int], FloatArray] | None = None,
        rotation_noise: float = 0.0,
        rotation_kernel: float = 0.0,
        rotation_kernel_max_spread: float = ROTATION_KERNEL_MAX_SPREAD,
        bias_walk: float = 0.0,
        count_rule: KldSampling | None = None,
    ) -> None:
        super().__init__(
            n_particles,
            area,
            rng=rng,
            resample=resample,
            ess_threshold=ess_threshold,
            reinject_fraction=reinject_fraction,
        )
        if not 0.0 <= rotation_kernel < 1.0:
            raise ValueError("rotation_kernel must be in [0, 1)")
        self.layout = layout
        self.extra_prior = (
            np.zeros(layout.width - layout.dim)
            if extra_prior is None
            else np.asarray(extra_prior, float)
        )
        if self.extra_prior.shape != (layout.width - layout.dim,):
            raise ValueError(f"extra_prior needs {layout.width - layout.dim} values")
        self.extra_sampler = extra_sampler
        """Draws ``m`` rows of the further blocks (``(m, width - dim)``: online bias beliefs
        about a sampled team offset, :meth:`relloc.localizers.priors.BiasPrior.beliefs`);
        ``None``: every particle at ``extra_prior``."""
        self.motion = motion or OdometryMotion()
        self.rotation_noise = rotation_noise
        """Random turn of the whole formation about the reference (rad/sqrt(s)) per predict:
        the one direction ranges cannot see, along which only the robots' headings inform the
        filter (their drift is this noise)."""
        self.rotation_kernel = rotation_kernel
        self.rotation_kernel_max_spread = rotation_kernel_max_spread
        self.rotation_kernel_count = 0
        self.kernel_paused = False
        """Set by :meth:`pause_kernel` while some robot is out of ranging: the formation is not
        one rigid body, and the orientation kernel waits."""
        self.bias_walk = bias_walk
        """Random walk of each online bias (m/sqrt(s)), added to its beliefs' variances."""
        self._others = np.array([layout.index(r) for r in layout.others], dtype=np.intp)
        self._reference = layout.index(layout.reference)
        self._noise = np.empty((0, layout.n_others, 2))
        """The buffer the NumPy ``predict`` draws the odometry noise into, reused while the
        count stays."""
        self.particles = self.sample_prior(n_particles)
        self._weights: FloatArray = np.empty(0)
        self._weights_of: FloatArray | None = None
        """``exp`` of the log-weights and the array it was computed from (:meth:`_exp_logw`)."""
        self._mcmc_scale = 0.5
        self.evidence = Evidence(len(layout.robots))
        """What was fused that can resolve the formation's orientation (for ``estimate``)."""
        self.count_rule = count_rule
        """The adaptive particle count (:mod:`relloc.filter.adaptive`); ``None``: fixed. Its
        ``max_particles`` is the count of every (re-)annealed start."""
        if count_rule is not None and count_rule.max_particles != n_particles:
            raise ValueError("count_rule.max_particles must be n_particles (the full count)")
        self.last_summary: ModeSummary | None = None
        """The summary of the last ``estimate`` since the last (re-)annealed start."""
        self.covariance_floor = 0.0
        """Variance (m^2) added per axis to the published covariances: the error the spread
        of the hypotheses cannot show (:mod:`relloc.filter.summary`; set by the localizer)."""

    # ---------------------------------------------------------------- prior
    def sample_prior(self, m: int) -> FloatArray:
        """``m`` particles uniform over the prior box of relative positions (further blocks at
        their prior values)."""
        out = np.empty((m, self.layout.width))
        out[:, : self.layout.dim] = self.prior.sample(self.rng, m, self.layout.n_others)
        out[:, self.layout.dim :] = self._extra(m)
        return out

    def _extra(self, m: int) -> FloatArray:
        """``m`` rows of the further blocks at their prior (module docstring)."""
        if self.extra_sampler is None or not self.extra_prior.size:
            return np.broadcast_to(self.extra_prior, (m, self.extra_prior.size))
        return self.extra_sampler(self.rng, m)

    def in_prior(self, particles: FloatArray) -> NDArray[np.bool_]:
        return self.prior.contains(particles[:, : self.layout.dim])

    def positions(self, particles: FloatArray | None = None) -> FloatArray:
        return self.layout.positions(self.particles if particles is None else particles)

    # ---------------------------------------------------------------- cycle
    def predict(self, disp: FloatArray, sigma: FloatArray, dt: float) -> None:
        """Move particles by every robot's displacement ``disp`` (N, 2) with std ``sigma`` (N,),
        turn each formation by ``rotation_noise`` and walk the online bias beliefs."""
        if not compiled.enabled():
            m, k = self.particles.shape[0], self.layout.n_others
            if self._noise.shape != (m, k, 2):
                self._noise = np.empty((m, k, 2))
        self.motion.propagate(
            self.particles, self._others, self._reference, disp, sigma, dt, self.rng, self._noise
        )
        self.evidence.moved(disp)
        if self.rotation_noise > 0.0 and dt > 0.0:
            self.rotate(self.rng.normal(0.0, self.rotation_noise * np.sqrt(dt), self.n))
        if self.layout.bias_pairs and dt > 0.0:
            self.particles[:, self.layout.dim + 1 :: 2] += self.bias_walk**2 * dt  # variances

    def update(self, models: Sequence[MeasurementModel]) -> bool:
        """Add the models' log-likelihoods to the log-weights and normalise, then let each
        model condition its sufficient statistics; False (weights kept) if no particle has any
        support."""
        if not models:
            return True
        self.evidence.fused(models)
        if compiled.enabled() and all(
            isinstance(model, RangeBatch) and model.fused for model in models
        ):
            return self._update_fused(models)  # type: ignore[arg-type]
        loglik = models[0].log_likelihood if len(models) == 1 else stacked(models)
        logw = renormalized(self.logw + self.log_likelihood(loglik, self.particles))
        if logw is not None:
            self.logw = logw
        positions = None
        for model in models:
            if model.conditions:
                positions = self.positions() if positions is None else positions
                model.condition(positions, self.particles)
        return logw is not None

    def _update_fused(self, batches: Sequence[RangeBatch]) -> bool:
        """:meth:`update` by range batches without online biases: each batch's compiled pass
        adds to a copy of the log-weights, one more normalises them and gives their ``exp``
        (kept for the estimate and the resampling)."""
        logw = self.logw.copy()
        for batch in batches:
            batch.add_log_likelihood(self.particles, self.layout, logw)
        w = np.empty_like(logw)
        if not renormalize_into(logw, w):
            return False
        self.logw = logw
        self._weights, self._weights_of = w, logw
        return True

    def log_likelihood(self, loglik: LogLikelihood, particles: FloatArray) -> FloatArray:
        """``loglik`` of every particle, evaluated in cache-sized blocks (non-finite -> -inf).

        Full-size temporaries of tens of thousands of particles times ranges fall out of the
        cache; blocks of a few thousand particles keep them in it.
        """
        m = particles.shape[0]
        out = np.empty(m)
        for start in range(0, m, _BLOCK):
            block = particles[start : start + _BLOCK]
            out[start : start + _BLOCK] = loglik(self.layout.positions(block), block)
        out[~np.isfinite(out)] = -np.inf
        return out

    def _exp_logw(self) -> FloatArray:
        """``exp(logw)``, computed once per log-weight array: the estimate and the resampling
        of one step share it (``logw`` is always replaced, never written in place)."""
        if self._weights_of is not self.logw:
            self._weights, self._weights_of = np.exp(self.logw), self.logw
        return self._weights

    def _select(self, idx: IntArray) -> None:
        self.particles = np.take(self.particles, idx, axis=0)  # several times faster than [idx]

    def resample(self) -> None:
        """:meth:`WeightedFilter.resample`; at a fixed count the systematic draw copies the
        rows in one compiled pass (:func:`~relloc.filter.resampling.systematic_take`, the same
        draw from the same uniform) instead of building the indices first."""
        if self.count_rule is not None or not compiled.enabled():
            super().resample()
            return
        out = np.empty_like(self.particles)
        systematic_take(self._exp_logw(), float(self.rng.random()), self.particles, out)
        self.particles = out
        self._finish_resample()

    def _reinject(self, slots: IntArray, positions: FloatArray) -> None:
        self.particles[slots, : self.layout.dim] = positions
        if self.extra_prior.size:
            self.particles[slots, self.layout.dim :] = self._extra(slots.size)

    def _after_resample(self) -> None:
        """Keep a team at rest on its ring, else the orientation kernel (module docstring),
        unless the localizer paused it (``kernel_paused``).

        While the exact posterior is invariant under the formation's symmetries (nothing but
        ranges fused, nobody moved: ``Evidence.symmetric``), resampling alone would narrow the
        ring onto the orientations of a few lucky ancestors, and the first motion would then
        choose among those instead of among all: a wrong orientation, confidently published.
        Re-spreading the resampled cloud over the symmetries is exact then, and keeps it
        uniform at any particle count."""
        if self.evidence.symmetric:
            self.spread_symmetries()
        elif (
            self.rotation_kernel > 0.0
            and not self.kernel_paused
            and self.rejuvenate_rotation(self.rotation_kernel)
        ):
            self.rotation_kernel_count += 1

    def counters(self) -> dict[str, int]:
        return {"rotation_kernel": self.rotation_kernel_count}

    def restart(
        self, recent: list[Any], reference: FloatArray | None, context: StartContext
    ) -> bool:
        """Recovery: the annealed start from ``recent`` (:mod:`relloc.filter.annealing`), each
        formation then turned to ``reference``'s orientation and handedness (``orient_by``)."""
        if not annealed_start(context, self, recent, shared_heading=self.shared_heading):
            return False
        if reference is not None:
            orient_by(self, reference)
        return True

    def pause_kernel(self, paused: bool) -> None:
        self.kernel_paused = paused

    # ---------------------------------------------------------------- particle count
    @property
    def posterior_wide(self) -> bool:
        """Whether the posterior is wide in a way the count rule's binning cannot see: no
        summary since the last (re-)annealed start, an orientation that is not observable,
        more than one mode (:mod:`relloc.filter.adaptive`), or the orientation kernel paused
        by the localizer (a robot out of ranging: the formation is not one rigid body, and
        only the count keeps the orientations of its parts diverse)."""
        s = self.last_summary
        return s is None or not s.orientation_observable or s.n_modes > 1 or self.kernel_paused

    def _resampled_size(self, idx: IntArray) -> int:
        """The count rule's size for the systematic draw ``idx`` (with repetitions): the cells
        are counted over the distinct particles it keeps."""
        if self.count_rule is None:
            return self.n
        if self.posterior_wide:
            return self.count_rule.max_particles
        kept = np.flatnonzero(np.bincount(idx, minlength=self.n))
        return self.count_rule.size(
            self.particles[kept, : self.layout.dim], wide=False, sigma=self.widest_std()
        )

    def widest_std(self) -> float:
        """Standard deviation (m) of the last summary's widest direction: the largest
        eigenvalue of any robot's published covariance, less the covariance floor."""
        s = self.last_summary
        if s is None:
            return math.inf
        top = float(np.linalg.eigvalsh(s.cov).max(initial=0.0))
        return math.sqrt(max(top - self.covariance_floor, 0.0))

    def _recovery_size(self) -> int:
        return self.n if self.count_rule is None else self.count_rule.max_particles

    def orientations(self) -> FloatArray:
        """Each particle's formation angle (rad) about the reference, relative to the
        coordinate-wise median formation (least-squares angle, weighted by distance)."""
        m = self.particles.shape[0]
        rel = self.particles[:, : self.layout.dim].reshape(m, -1, 2)
        ref = np.median(rel, axis=0)  # robust to re-injected prior particles and stray modes
        cross = rel[:, :, 1] @ ref[:, 0] - rel[:, :, 0] @ ref[:, 1]
        dot = rel[:, :, 0] @ ref[:, 0] + rel[:, :, 1] @ ref[:, 1]
        return np.arctan2(cross, dot)

    def rejuvenate_rotation(self, h: float) -> bool:
        """Liu-West kernel along the formation's orientation on equally weighted particles:
        turn each particle of the main mode from ``theta`` to
        ``a theta + (1 - a) mean + sqrt(h) std eps`` (``a = sqrt(1 - h)``), keeping the mean and
        variance of the orientations. Particles farther than 4 robust stds from the mode (other
        modes, re-injected ones) are left alone. Returns False (and does nothing) when the
        orientations do not form one mode narrower than ``rotation_kernel_max_spread``, or
        when there is no formation (a single non-reference robot)."""
        if len(self.layout.others) < 2:
            return False
        theta = self.orientations()
        d = np.remainder(theta - np.median(theta) + np.pi, 2.0 * np.pi) - np.pi
        spread = 1.4826 * float(np.median(np.abs(d)))
        if not 0.0 < spread < self.rotation_kernel_max_spread:
            return False
        core = np.abs(d) < 4.0 * spread
        dc = d[core]
        mean, std = float(dc.mean()), float(dc.std())
        a = np.sqrt(1.0 - h)
        turn = np.zeros(self.particles.shape[0])
        eps = self.rng.standard_normal(dc.size)
        turn[core] = (a - 1.0) * dc + (1.0 - a) * mean + np.sqrt(h) * std * eps
        self.rotate(turn)
        return True

    def estimate(self) -> FilterEstimate:
        """The posterior's honest summary (:func:`relloc.filter.summary.summarize`): the
        dominant mode's mean and covariance of each robot's relative position (the ring's
        moments while the orientation cannot have been resolved), with the mode's weight, the
        shape and the pairwise distances; and the mixture moments of each online bias. The
        shape and the distances are computed when first read
        (:class:`~relloc.filter.summary.DeferredSummary`): a step nobody publishes skips them."""
        w = self._exp_logw()
        m = self.particles.shape[0]
        if compiled.enabled():
            summary = summarize_particles(
                self.particles,
                self.layout.n_others,
                w,
                can_resolve=self.evidence.can_resolve,
                floor=self.covariance_floor,
                deferred=True,
            )
        else:
            summary = summarize(
                self.particles[:, : self.layout.dim].reshape(m, -1, 2),
                w,
                can_resolve=self.evidence.can_resolve,
                floor=self.covariance_floor,
                deferred=True,
            )
        self.last_summary = summary
        biases = {}
        for pair in self.layout.bias_pairs:
            c, _ = self.layout.bias_columns(pair)
            biases[pair] = mixture_moments(w, self.particles[:, c], self.particles[:, c + 1])
        return FilterEstimate(
            mean=summary.mean,
            cov=summary.cov,
            ess=float(1.0 / np.einsum("m,m->", w, w)),
            biases=biases,
            summary=summary,
            particles=m,
        )

    # ---------------------------------------------------------------- initialisation
    def initialize_annealed(
        self,
        loglik: LogLikelihood,
        guide: LogLikelihood | None = None,
        *,
        max_stages: int = 60,
        mcmc_steps: int = MCMC_STEPS,
        target_ess: float = 0.5,
    ) -> int:
        """Move the particles from the prior to ``prior * L`` by likelihood tempering.

        At each stage the next temperature is found by bisection so that the incremental
        weights keep an effective sample size of ``target_ess * M``; the particles are then
        resampled and moved by ``mcmc_steps`` random-walk Metropolis steps targeting
        ``prior * G^beta``, the proposal scaled to the particle spread and adapted to the
        acceptance rate.

        ``guide`` (default: ``loglik``) is the likelihood that is tempered. A robust likelihood
        with a uniform outlier floor is flat beyond a few sigma at *every* temperature and so
        cannot guide particles from far away; tempering a plain Gaussian ``guide`` instead, and
        correcting to ``loglik`` by importance weights at the end, reaches the same target.
        Returns the number of stages used.
        """
        guide = guide or loglik
        if self.count_rule is not None:
            self.n = self.count_rule.max_particles  # a wide posterior: the full count
        self.last_summary = None
        self.particles = self.sample_prior(self.n)
        ll = self.log_likelihood(guide, self.particles)
        beta = 0.0
        stages = 0
        self._mcmc_scale = 0.5
        while beta < 1.0 and stages < max_stages:
            stages += 1
            beta_next = self._next_temperature(ll, beta, target_ess)
            logw = (beta_next - beta) * np.where(np.isfinite(ll), ll, -1e300)
            beta = beta_next
            idx = systematic_resample(np.exp(log_normalize(logw)), self.rng)
            self.particles, ll = self.particles[idx], ll[idx]
            ll = self._metropolis(guide, ll, beta, mcmc_steps)
        if guide is not loglik or beta < 1.0:
            # The particles follow prior * guide^beta: weigh them to prior * loglik (also when
            # max_stages stopped the tempering short of beta = 1).
            target = self.log_likelihood(loglik, self.particles) if guide is not loglik else ll
            ok = np.isfinite(target) & np.isfinite(ll)
            logw = np.where(ok, target - beta * np.where(ok, ll, 0.0), -1e300)
            idx = systematic_resample(np.exp(log_normalize(logw)), self.rng)
            self.particles = self.particles[idx]
            self._metropolis(loglik, target[idx], 1.0, mcmc_steps)
        self.logw = np.full(self.n, -np.log(self.n))
        return stages

    def _next_temperature(self, ll: FloatArray, beta: float, target_ess: float) -> float:
        finite = np.where(np.isfinite(ll), ll, -1e300)
        if ess((1.0 - beta) * finite) >= target_ess * self.n:
            return 1.0
        lo, hi = beta, 1.0
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if ess((mid - beta) * finite) >= target_ess * self.n:
                lo = mid
            else:
                hi = mid
        return max(lo, beta + 1e-6)

    def _metropolis(
        self, loglik: LogLikelihood, ll: FloatArray, beta: float, steps: int
    ) -> FloatArray:
        """Random-walk Metropolis on ``prior * L^beta``; the step adapts to the acceptance rate."""
        spread = np.std(self.particles, axis=0) + 1e-3
        for _ in range(steps):
            proposal = self.particles.copy()
            d = self.layout.dim  # only the positions are sampled; other blocks ride along
            proposal[:, :d] += self.rng.standard_normal((self.n, d)) * (
                self._mcmc_scale * spread[:d]
            )
            ll_prop = self.log_likelihood(loglik, proposal)
            log_ratio = beta * (ll_prop - ll)
            accept = self.in_prior(proposal) & (np.log(self.rng.random(self.n)) < log_ratio)
            self.particles[accept] = proposal[accept]
            ll = np.where(accept, ll_prop, ll)
            rate = accept.mean()
            if rate < 0.15:
                self._mcmc_scale = max(self._mcmc_scale * 0.5, 1e-3)
            elif rate > 0.4:
                self._mcmc_scale = min(self._mcmc_scale * 1.5, 1.0)
        return ll

    def spread_symmetries(self, reflections: bool = True) -> None:
        """Rotate each particle's formation about the reference by a uniform random angle,
        and mirror it with probability 1/2: the symmetries that ranges alone cannot resolve."""
        m = self.particles.shape[0]
        rel = self.particles[:, : self.layout.dim].reshape(m, -1, 2).copy()
        if reflections:
            flip = self.rng.random(m) < 0.5
            rel[flip, :, 1] *= -1.0
        self.particles[:, : self.layout.dim] = rel.reshape(m, -1)
        self.rotate(np.asarray(self.rng.uniform(-np.pi, np.pi, m), float))

    def rotate(self, theta: FloatArray) -> None:
        """Turn particle ``k``'s formation about the reference by ``theta[k]`` (rad)."""
        m = self.particles.shape[0]
        rel = self.particles[:, : self.layout.dim].reshape(m, -1, 2)
        c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
        x, y = rel[:, :, 0].copy(), rel[:, :, 1].copy()
        rel[:, :, 0] = c * x - s * y
        rel[:, :, 1] = s * x + c * y
