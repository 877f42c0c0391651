"""The self-calibrating localizer: headings, odometry scales and range biases estimated online.

Where the config says ``heading_mode = "estimate"`` or ``odom_scale_mode = "online"``, the
quantities a sampled particle cannot integrate (a heading revealed a little at every step) are
carried by a Gaussian-sum filter (:mod:`relloc.estimators.gaussian_sum.filter`, which explains why): each
of its components is a Kalman filter over positions and calibration. It starts from the
sampled filter's annealed start (:mod:`relloc.filter.annealing`), one Gaussian per particle,
after which the sampled filter is dropped.

What the filter estimates is not read from the config: a robot's odometry track keeps its own
frame (heading estimated) or its raw length (scale estimated). With estimated headings there is
no compass frame, so detection vectors cannot be fused; every range uses the symmetric model.
"""

from __future__ import annotations

import math

import numpy as np

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.estimators.gaussian_sum.filter import (
    CalibrationLayout,
    CalibrationNoise,
    GaussianSumFilter,
)
from relloc.estimators.particle.filter import ParticleFilter
from relloc.estimators.particle.localizer import particle_filter
from relloc.filter.annealing import annealed_start
from relloc.filter.resampling import normalize, systematic_resample
from relloc.localizers.base import Measurement
from relloc.localizers.bounds import CalibrationBounds
from relloc.localizers.filtered import FilterLocalizer
from relloc.localizers.priors import bias_layout, covariance_floor


def calibration_layout(config: TeamConfig) -> CalibrationLayout:
    """Which calibration blocks the config asks to estimate (the layout of the filter)."""
    fc = config.filter
    layout, _ = bias_layout(config)
    return CalibrationLayout(
        layout.robots,
        layout.reference,
        heading=fc.self_calibration.heading_mode == "estimate",
        scale=fc.self_calibration.odom_scale_mode == "online",
        bias_pairs=layout.bias_pairs,
        rates=layout.robots if fc.self_calibration.gyro_bias_sigma > 0.0 else (),
    )


class SelfCalibratingLocalizer(FilterLocalizer):
    """Odometry + UWB ranges in a Gaussian-sum filter that estimates the calibration."""

    method = "pf"
    range_model = "symmetric"
    filter: GaussianSumFilter

    def __init__(self, config: TeamConfig, *, seed: int = 0, method: str = "pf") -> None:
        # independent pair priors: a pair's columns already hold its time-correlated error
        layout, prior = bias_layout(config, team=False, nodes=False)
        self.calibration = calibration_layout(config)
        super().__init__(config, layout, seed=seed)
        self.method = method
        self.watchdog.range_model = self.range_model  # judged with the noise this filter assumes
        fc = config.filter
        self.filter = self._gaussian_sum(np.array(prior.flat()))
        self.filter.covariance_floor = covariance_floor(config, self.range_model)
        gsf = self.filter
        self.bounds = CalibrationBounds(
            config,
            {
                pair: (float(m), math.sqrt(float(v)))
                for pair, m, v in zip(
                    self.calibration.bias_pairs,
                    gsf.bias_prior_mean,
                    gsf.bias_prior_var,
                    strict=True,
                )
            },
        )
        # the annealed start: a sampled filter over positions (and bias beliefs)
        n_start = max(
            fc.self_calibration.selfcal_init_particles, fc.self_calibration.selfcal_particles
        )
        self.start_filter: ParticleFilter | None = particle_filter(
            config, layout, prior, n_start, self.rng
        )

    def _track_frame(self, robot: str) -> tuple[float, float]:
        """The config's heading offset and scale, unless the filter estimates them: then the
        track keeps the robot's own frame (offset 0) or its raw length (scale 1)."""
        offset, scale = super()._track_frame(robot)
        return (
            0.0 if self.calibration.heading else offset,
            1.0 if self.calibration.scale else scale,
        )

    def _gaussian_sum(self, bias_prior: np.ndarray) -> GaussianSumFilter:
        fc, layout = self.config.filter, self.calibration
        prior = (bias_prior[0::2], bias_prior[1::2]) if len(layout.bias_pairs) else None
        heading_prior: dict[str, tuple[float, float]] = {}
        if layout.heading and fc.self_calibration.heading_prior_sigma_deg > 0.0:
            ref = self.config.robot(layout.reference).heading_offset
            for robot in layout.others:
                angle = math.remainder(self.config.robot(robot).heading_offset - ref, math.tau)
                heading_prior[robot] = (
                    angle,
                    math.radians(fc.self_calibration.heading_prior_sigma_deg),
                )
        noise = CalibrationNoise(
            heading_walk=fc.self_calibration.heading_walk,
            reference_heading_walk=fc.self_calibration.reference_heading_walk,
            bias_walk=fc.self_calibration.bias_walk,
            rate_sigma=fc.self_calibration.gyro_bias_sigma,
            scale_bounds=(fc.self_calibration.scale_min, fc.self_calibration.scale_max),
        )
        return GaussianSumFilter(
            layout,
            fc.self_calibration.selfcal_particles,
            self.config.area,
            rng=self.rng,
            noise=noise,
            bias_prior=prior,
            position_sigma=fc.self_calibration.selfcal_position_sigma,
            heading_prior=heading_prior,
            split_heading_std=fc.self_calibration.heading_split_std,
        )

    def _restart_calibration(self) -> bool:
        """Every Gaussian's calibration back at its prior, its positions kept (their spread
        back to the start's), its weight kept."""
        gsf = self.filter
        logw = gsf.logw.copy()
        gsf.initialize(gsf.mean[:, : gsf.layout.dim].copy())
        gsf.logw = logw
        if self.bounds is not None:
            self.bounds.restart()
        return True

    def _start(self, t: float, batch: list[Measurement]) -> Estimate | None:
        """Anneal the sampled start, then hand its particles to the Gaussian-sum filter (one
        Gaussian per particle, resampled to its size) and drop the sampled filter."""
        pf = self.start_filter
        assert pf is not None
        if not annealed_start(self, pf, batch, shared_heading=self.filter.shared_heading):
            return None
        self._started(t)
        gsf, particles = self.filter, pf.particles
        if particles.shape[0] != gsf.n or np.ptp(pf.logw) > 0.0:  # (the vectors' weights)
            idx = systematic_resample(normalize(pf.logw), self.rng, gsf.n)
            particles = particles[idx]
        gsf.initialize(particles[:, : 2 * self.layout.n_others])
        self.start_filter = None
        fe = gsf.estimate()
        return self._emit(t, fe, self._body(t, fe))
