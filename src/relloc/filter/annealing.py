"""The annealed start: the first posterior from the uniform prior, up to the formation's
symmetries.

A uniform prior over the arena is very wide compared with a range's noise, so the first batch
(``init_window`` of measurements) is fused by likelihood tempering
(:meth:`relloc.estimators.particle.filter.ParticleFilter.initialize_annealed`), guided by the plain Gaussian
likelihood (a robust one is flat far from the target at every temperature).

Models invariant under a rotation or reflection of the formation about the reference (ranges)
cannot tell those images apart, and a sharp likelihood would pick one by chance. So the start
anneals on the invariant models only, spreads the particles uniformly over rotations and
mirror images (exact for an invariant target), and only then weighs them by the other models
(a detection vector fixes the orientation). With no invariant model in the batch it anneals on
everything and does not spread. Both particle localizers start so; the self-calibrating one
then hands the particles to its Gaussian-sum filter. A particle filter's recovery restart
(:meth:`relloc.estimators.particle.filter.ParticleFilter.restart`) is the same start from the recent
measurements, each formation then turned to the orientation of a trusted one
(:func:`orient_by`).

The start asks its localizer only for the measurement models of some events
(:class:`StartContext`), so this module knows no localizer.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from relloc.filter.measurement import MeasurementModel, stacked
from relloc.filter.registry import model_for

if TYPE_CHECKING:
    from relloc.filter.state import StateLayout

FloatArray = NDArray[np.float64]

MCMC_STEPS = 3
"""Metropolis moves per temperature of the annealed start
(:meth:`relloc.estimators.particle.filter.ParticleFilter.initialize_annealed`): enough to re-create the diversity
each tempered resampling takes away."""
REFERENCE_SIGMA = 0.5
"""Scale (m) of the robust fit of a re-annealed formation to the dead-reckoned reference: a
robot farther off than this (moved unseen) hardly sways the orientation."""


class Annealable(Protocol):
    """What the start asks of a particle filter (:class:`relloc.estimators.particle.filter.ParticleFilter`)."""

    particles: FloatArray

    @property
    def layout(self) -> StateLayout: ...

    def initialize_annealed(
        self, loglik: Callable[[FloatArray, FloatArray], FloatArray],
        guide: Callable[[FloatArray, FloatArray], FloatArray] | None = None, *, mcmc_steps: int = MCMC_STEPS,
    ) -> int: ...  # fmt: skip

    def spread_symmetries(self) -> None: ...

    def update(self, models: Sequence[MeasurementModel]) -> bool: ...

    def maybe_resample(self) -> bool: ...

    def rotate(self, theta: FloatArray) -> None: ...


class StartContext(Protocol):
    """What the start asks of its localizer: the statistics it counts into, and the measurement
    models of some events for a given filter (robust, or the plain guide)."""

    stats: Counter[str]

    def models(
        self, batch: list[Any], target: Any, *, robust: bool = True, count: bool = True
    ) -> list[MeasurementModel]: ...


def annealed_start(
    context: StartContext, pf: Annealable, batch: list[Any], *, shared_heading: bool
) -> bool:
    """Start ``pf`` from ``batch`` (module docstring); False if the batch gives it nothing to
    anneal on. ``shared_heading``: whether the localizer's filter has the shared heading frame
    (what makes a sighting invariant or not). Counts the tempering stages and any resampling in
    ``context.stats``."""
    invariant = [m for m in batch if _invariant(m, shared_heading)]
    spread = bool(context.models(invariant, pf, count=False))
    anneal_on = invariant if spread else batch
    models = context.models(anneal_on, pf, count=False)
    guide = context.models(anneal_on, pf, robust=False, count=False)
    if not models or not guide:
        return False
    stages = pf.initialize_annealed(stacked(models), stacked(guide))
    context.stats["anneal_stages"] = stages
    if spread:
        pf.spread_symmetries()
        rest = context.models(
            [m for m in batch if not _invariant(m, shared_heading)], pf, count=False
        )
        if rest:
            pf.update(rest)
            if pf.maybe_resample():
                context.stats["resampled"] += 1
    return True


def _invariant(event: object, shared_heading: bool) -> bool:
    """Whether ``event``'s model is invariant; a model that needs a heading only for its
    non-invariant part (a sighting's bearing) is invariant where the filter has none."""
    model = model_for(event)
    if model is None:
        return False
    return model.invariant or (
        not shared_heading and getattr(model, "invariant_without_shared_heading", False)
    )


def orient_by(pf: Annealable, reference: FloatArray, sigma: float = REFERENCE_SIGMA) -> None:
    """Turn (and, where it fits better, mirror) each particle's formation to the orientation
    that best fits ``reference`` (relative positions ``(2(N-1),)``): the orientation and
    handedness of a re-annealed start, whose ranges fixed only the shape. Shapes are left as
    the ranges made them; the weights are not touched.

    The fit is a 2D Procrustes rotation of each particle's robots, the reference robot among
    them, about their centroids, for the particle and for its mirror image. A robot whose
    position ``reference`` gets wrong (it was moved unseen; the reference robot itself, too)
    is down-weighted by iterating with Cauchy weights ``1 / (1 + r^2 / sigma^2)`` of the
    previous residuals ``r`` (iteratively reweighted least squares); the image with the
    smaller robust residual is kept. Vectorised over particles."""
    m, d = pf.particles.shape[0], pf.layout.dim
    pts = np.concatenate([np.zeros((m, 1, 2)), pf.particles[:, :d].reshape(m, -1, 2)], axis=1)
    ref = np.concatenate([np.zeros((1, 2)), np.asarray(reference, float).reshape(-1, 2)])
    mirrored = pts * np.array([1.0, -1.0])
    theta, cost = _procrustes(pts, ref, sigma)
    theta_m, cost_m = _procrustes(mirrored, ref, sigma)
    flip = cost_m < cost
    rel = np.where(flip[:, None, None], mirrored, pts)[:, 1:]
    pf.particles[:, :d] = rel.reshape(m, -1)
    pf.rotate(np.where(flip, theta_m, theta))


def _procrustes(
    pts: FloatArray, ref: FloatArray, sigma: float, passes: int = 3
) -> tuple[FloatArray, FloatArray]:
    """Per particle, the robust rotation (rad) of ``pts`` ``(M, N, 2)`` onto ``ref`` ``(N, 2)``
    about the centroids, and its cost (the sum of ``log(1 + r^2 / sigma^2)``)."""
    w = np.ones(pts.shape[:2])
    theta = np.zeros(pts.shape[0])
    residual = np.zeros(pts.shape[:2])
    for _ in range(passes):
        ws = w / w.sum(axis=1, keepdims=True)
        a = pts - np.einsum("mn,mnk->mk", ws, pts)[:, None]
        b = ref[None] - (ws @ ref)[:, None]
        cross = np.einsum("mn,mn->m", w, a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])
        dot = np.einsum("mn,mn->m", w, a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1])
        theta = np.arctan2(cross, dot)
        c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
        residual = np.hypot(
            c * a[..., 0] - s * a[..., 1] - b[..., 0], s * a[..., 0] + c * a[..., 1] - b[..., 1]
        )
        w = 1.0 / (1.0 + (residual / sigma) ** 2)
    return theta, np.log1p((residual / sigma) ** 2).sum(axis=1)
