"""The sampled localizer: odometry + UWB ranges (+ detection vectors) in a particle filter.

Every particle is one hypothesis about the formation (:mod:`relloc.filter.pf`); with online
biases (``bias_mode = "online"``) it also carries a Gaussian belief about each UWB node pair's
range bias, its prior the pair's calibration where there is one, else ``uwb.default_bias`` +-
``uwb.default_bias_sigma``, what the default mode assumes (Rao-Blackwellised,
:mod:`relloc.filter.state`). The range model updates
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
from relloc.events import pair_key
from relloc.filter.adaptive import MIN_PARTICLES_NO_KERNEL, KldSampling
from relloc.filter.annealing import annealed_start
from relloc.filter.pf import ParticleFilter
from relloc.filter.state import StateLayout
from relloc.localizers.base import Measurement
from relloc.localizers.filtered import FilterLocalizer

BIAS_PRIOR_SIGMA = 0.05
"""Online biases: prior standard deviation (m) of a calibrated pair's bias about its
calibration (the spread of the pair biases between sessions)."""
BIAS_PRIOR_SIGMA_UNCALIBRATED = 0.25
"""Online biases in the Gaussian-sum filter (headings or scales estimated as well): prior
standard deviation (m) of an uncalibrated pair's bias. The sampled filter uses
``uwb.default_bias_sigma`` instead, the width its default mode assumes for the same pair: a
wider prior let the bias run, on a new session, along what one range cannot tell apart (a
longer bias, a nearer robot) (docs/self-calibration.md, "Online bias on a new session")."""


def bias_layout(
    config: TeamConfig, *, uncalibrated_sigma: float | None = None
) -> tuple[StateLayout, list[float]]:
    """The sampled state's layout and the prior of its non-position columns: with online
    biases a (mean, variance) belief per UWB node pair of the team, none otherwise. An
    uncalibrated pair's prior is ``uwb.default_bias`` +- ``uncalibrated_sigma`` (default:
    ``BIAS_PRIOR_SIGMA_UNCALIBRATED``), a calibrated pair's its bias +- ``BIAS_PRIOR_SIGMA``."""
    fc = config.filter
    names = config.robot_names
    if fc.self_calibration.bias_mode != "online":
        return StateLayout(names, config.reference), []
    node_pairs = sorted(
        {_node_pair(config, a, b) for i, a in enumerate(names) for b in names[i + 1 :]}
    )
    prior: list[float] = []
    for pair in node_pairs:
        cal = config.uwb.pairs.get(pair)
        if cal is not None:
            prior += [cal.bias, BIAS_PRIOR_SIGMA**2]
        else:
            sigma = (
                BIAS_PRIOR_SIGMA_UNCALIBRATED if uncalibrated_sigma is None else uncalibrated_sigma
            )
            prior += [config.uwb.default_bias, sigma**2]
    return StateLayout(names, config.reference, tuple(node_pairs)), prior


def _node_pair(config: TeamConfig, robot_a: str, robot_b: str) -> str:
    """Key of the UWB transceiver pair between two robots (robot names if no node ids)."""
    a = config.robot(robot_a).uwb_node or robot_a
    b = config.robot(robot_b).uwb_node or robot_b
    return pair_key(a, b)


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
    prior: list[float],
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
        extra_prior=np.array(prior),
        rotation_noise=fc.odometry.rotation_noise,
        rotation_kernel=fc.resampling.rotation_kernel,
        bias_walk=fc.self_calibration.bias_walk,
        count_rule=rule,
    )


def covariance_floor(config: TeamConfig, range_model: str) -> float:
    """Variance (m^2) per axis the filter adds to what it publishes: one range's noise under
    the localizer's range model (``[uwb] los_sigma``, or ``sigma`` for the symmetric model).
    Range errors are correlated in time, so fusing many cannot average them below that
    (:mod:`relloc.filter.summary`)."""
    sigma = config.uwb.los_sigma if range_model == "nlos" else config.uwb.sigma
    return float(sigma) ** 2


class ParticleFilterLocalizer(FilterLocalizer):
    """Odometry + UWB ranges (+ relative observations from detections) in a particle filter."""

    method = "pf"
    filter: ParticleFilter

    def __init__(self, config: TeamConfig, *, seed: int = 0, method: str = "pf") -> None:
        # An uncalibrated pair's online bias starts from what the default mode assumes about it,
        # default_bias +- default_bias_sigma (docs/self-calibration.md, "Online bias on a new session").
        layout, prior = bias_layout(config, uncalibrated_sigma=config.uwb.default_bias_sigma)
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
