"""The annealed start: the first posterior from the uniform prior, up to the formation's
symmetries.

A uniform prior over the arena is very wide compared with a range's noise, so the first batch
(``init_window`` of measurements) is fused by likelihood tempering
(:meth:`relloc.filter.pf.ParticleFilter.initialize_annealed`), guided by the plain Gaussian
likelihood (a robust one is flat far from the target at every temperature).

Models invariant under a rotation or reflection of the formation about the reference (ranges)
cannot tell those images apart, and a sharp likelihood would pick one by chance. So the start
anneals on the invariant models only, spreads the particles uniformly over rotations and
mirror images (exact for an invariant target), and only then weighs them by the other models
(a detection vector fixes the orientation). With no invariant model in the batch it anneals on
everything and does not spread. Used by both particle localizers: the sampled one keeps the
particles, the self-calibrating one hands them to its Gaussian-sum filter.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from relloc.filter.measurement import stacked
from relloc.filter.pf import ParticleFilter
from relloc.filter.registry import model_for

if TYPE_CHECKING:
    from relloc.localizers.base import FilterLocalizer, Measurement


def annealed_start(localizer: FilterLocalizer, pf: ParticleFilter, batch: list[Measurement]) -> bool:
    """Start ``pf`` from ``batch`` (module docstring); False if the batch gives it nothing to
    anneal on. Counts the tempering stages and any resampling in ``localizer.stats``."""
    fc = localizer.config.filter
    shared = localizer.filter.shared_heading
    invariant = [m for m in batch if _invariant(m, shared)]
    spread = fc.spread_rotations and bool(localizer.models(invariant, pf, count=False))
    anneal_on = invariant if spread else batch
    models = localizer.models(anneal_on, pf, count=False)
    guide = localizer.models(anneal_on, pf, robust=False, count=False)
    if not models or not guide:
        return False
    stages = pf.initialize_annealed(stacked(models), stacked(guide), mcmc_steps=fc.mcmc_steps)
    localizer.stats["anneal_stages"] = stages
    if spread:
        pf.spread_symmetries()
        rest = localizer.models([m for m in batch if not _invariant(m, shared)], pf, count=False)
        if rest:
            pf.update(rest)
            if pf.maybe_resample():
                localizer.stats["resampled"] += 1
    return True


def _invariant(event: object, shared_heading: bool) -> bool:
    """Whether ``event``'s model is invariant; a model that needs a heading only for its
    non-invariant part (a sighting's bearing) is invariant where the filter has none."""
    model = model_for(event)
    if model is None:
        return False
    return model.invariant or (not shared_heading and getattr(model, "invariant_without_shared_heading", False))
