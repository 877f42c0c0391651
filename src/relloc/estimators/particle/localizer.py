"""The sampled localizer: odometry + UWB ranges (+ detection vectors) in a particle filter.

Every particle is one hypothesis about the formation (:mod:`relloc.estimators.particle.filter`); with online
biases (``bias_mode = "online"``) it also carries a Gaussian belief about each UWB node pair's
range bias, its prior the pair's calibration where there is one, else ``uwb.default_bias``
plus a team offset the particle draws (``uwb.team_offset_sigma``) +- ``uwb.default_bias_sigma``
(Rao-Blackwellised given the offset, :mod:`relloc.filter.state`;
:class:`relloc.localizers.priors.BiasPrior`). The range model updates
those beliefs; the filter walks their variances. The particle count adapts
(``[filter.adaptive]``, :mod:`relloc.filter.adaptive`): ``[filter] particles`` at the start and
while the posterior is wide, down to ``min_particles`` once it is one narrow mode. The
localizer itself only starts the filter
(:mod:`relloc.filter.annealing`) and then runs the cycle of
:class:`~relloc.localizers.filtered.FilterLocalizer`; its recovery re-anneals
(``ParticleFilter.restart``).
"""

from __future__ import annotations

import numpy as np

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.estimators.particle.filter import ParticleFilter
from relloc.filter.adaptive import MIN_PARTICLES_NO_KERNEL, KldSampling
from relloc.filter.annealing import annealed_start
from relloc.filter.state import StateLayout
from relloc.localizers.base import Measurement
from relloc.localizers.filtered import FilterLocalizer
from relloc.localizers.priors import BiasPrior, bias_layout, covariance_floor


def count_rule(config: TeamConfig, layout: StateLayout) -> KldSampling | None:
    """The adaptive particle count of ``[filter.adaptive]`` for ``layout`` (``None`` where it
    is ``fixed``): from ``[filter] particles`` down to ``min_particles``, or to
    ``MIN_PARTICLES_NO_KERNEL`` where the orientation kernel cannot act (a single
    non-reference robot, or no kernel), each at most ``particles``."""
    fc = config.filter
    ac = fc.adaptive
    if ac.particle_count == "fixed":
        return None
    kernel = fc.resampling.rotation_kernel > 0.0 and layout.n_others >= 2
    floor = ac.min_particles if kernel else MIN_PARTICLES_NO_KERNEL
    return KldSampling(min(floor, fc.particles), fc.particles, mc_tolerance=ac.mc_tolerance)


def particle_filter(
    config: TeamConfig,
    layout: StateLayout,
    prior: BiasPrior,
    n: int,
    rng: np.random.Generator,
    rule: KldSampling | None = None,
) -> ParticleFilter:
    """The configured particle filter of ``n`` particles over ``layout`` (with the adaptive
    count ``rule``, if any: ``n`` is then its maximum)."""
    fc = config.filter
    return ParticleFilter(
        layout,
        n,
        config.area,
        rng=rng,
        extra_prior=np.array(prior.flat()),
        extra_sampler=prior.beliefs,
        rotation_noise=fc.odometry.rotation_noise,
        rotation_kernel=fc.resampling.rotation_kernel,
        bias_walk=fc.self_calibration.bias_walk,
        count_rule=rule,
    )


class ParticleFilterLocalizer(FilterLocalizer):
    """Odometry + UWB ranges (+ relative observations from detections) in a particle filter."""

    method = "pf"
    filter: ParticleFilter

    def __init__(self, config: TeamConfig, *, seed: int = 0, method: str = "pf") -> None:
        # An uncalibrated pair's online bias starts from what the default mode assumes about it,
        # default_bias +- default_bias_sigma (docs/explanation/self-calibration.md, "Online bias on a new session").
        # no node offsets: sampled, not Rao-Blackwellised, five more dimensions thin the particles
        layout, prior = bias_layout(
            config, uncalibrated_sigma=config.uwb.default_bias_sigma, nodes=False
        )
        super().__init__(config, layout, seed=seed)
        self.method = method
        self.range_model = (
            config.filter.likelihood.range_model
        )  # online pairs too (RangeBatch.build)
        self.watchdog.particle_biases = True
        self.filter = particle_filter(
            config, layout, prior, config.filter.particles, self.rng, count_rule(config, layout)
        )
        self.filter.covariance_floor = covariance_floor(config, self.range_model)

    def _start(self, t: float, batch: list[Measurement]) -> Estimate | None:
        if not annealed_start(self, self.filter, batch, shared_heading=self.filter.shared_heading):
            return None
        self._started(t)
        return self._emit(t, self.filter.estimate())
