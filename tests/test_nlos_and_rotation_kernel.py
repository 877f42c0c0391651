"""The NLOS-aware range likelihood and the orientation kernel of the particle filter.

Both answer the shortbag's loss to multilateration (``docs/explanation/measurements.md``): UWB ranges are skewed (a blocked path can only make a
range longer), and resampling loses the diversity of the formation's orientation about the
reference, the one direction ranges cannot see.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from relloc.config import FilterConfig
from relloc.estimators.particle.filter import ParticleFilter
from relloc.filter.ranges import RangeBatch, range_mixture
from relloc.filter.state import StateLayout


def _batch(z: float, sigma: float = 0.1, **kw) -> RangeBatch:
    return RangeBatch(
        np.array([0]), np.array([1]), np.array([z]), np.array([0.0]), np.array([sigma]), **kw
    )


def _positions(xs: list[float]) -> np.ndarray:
    pos = np.zeros((2, 2, len(xs)))  # (xy, robot, particle): robot 1 at x, robot 0 at origin
    pos[0, 1, :] = xs
    return pos


def test_nlos_mixture_is_a_density_with_the_stated_parts() -> None:
    r = np.linspace(-4.0, 6.0, 200_001)
    dr = r[1] - r[0]
    los, total = range_mixture(r, np.array(0.1), 0.0, 15.0, 0.1, 0.3)
    assert total.sum() * dr == pytest.approx(1.0, abs=1e-6)
    assert los.sum() * dr == pytest.approx(0.9, abs=1e-6)
    _, with_floor = range_mixture(r, np.array(0.1), 0.02, 15.0, 0.1, 0.3)
    assert np.min(with_floor) >= 0.02 / 15.0


def test_a_long_range_is_explained_as_a_blocked_path_a_short_one_is_not() -> None:
    nlos = _batch(2.0, outlier_fraction=0.02, nlos_fraction=0.1, nlos_sigma=0.3)
    ll = nlos.log_likelihood(
        _positions([1.6, 2.4, 2.0])
    )  # range 0.4 m too long / too short / right
    assert ll[0] > ll[1] + 2.0  # too long: plausible NLOS; too short: only the gross-error floor
    assert ll[2] > ll[0]
    # a particle 0.3 m short of a long (NLOS) range is penalised less than by the Gaussian alone
    # (2.9 against 4.5 nats); one 0.3 m too long is penalised as by the Gaussian
    gauss = _batch(2.3, outlier_fraction=0.0)
    skew = _batch(2.3, outlier_fraction=0.02, nlos_fraction=0.1, nlos_sigma=0.3)
    pos = _positions([2.0, 2.3, 2.6])
    g, s = gauss.log_likelihood(pos), skew.log_likelihood(pos)
    assert (s[1] - s[0]) < 0.7 * (g[1] - g[0])
    assert (s[1] - s[2]) > 0.9 * (g[1] - g[2])


def test_without_nlos_part_the_symmetric_model_is_unchanged() -> None:
    pos = _positions([1.0, 2.0, 3.0])
    a = _batch(2.3, outlier_fraction=0.1).log_likelihood(pos)
    b = _batch(2.3, outlier_fraction=0.1, nlos_fraction=0.0, nlos_sigma=0.5).log_likelihood(pos)
    np.testing.assert_array_equal(a, b)


def test_online_bias_learns_less_from_a_long_range_than_from_a_short_one() -> None:
    particles = np.array([[2.0, 0.0, 0.0, 0.05**2]])  # x, y of robot 1; bias mean, variance
    pos = _positions([2.0])

    def moved(z: float) -> float:
        p = particles.copy()
        batch = RangeBatch(
            np.array([0]),
            np.array([1]),
            np.array([z]),
            np.array([0.0]),
            np.array([0.1]),
            outlier_fraction=0.02,
            bias_columns=np.array([2]),
            nlos_fraction=0.1,
            nlos_sigma=0.3,
        )
        batch.condition(pos, p)
        return abs(p[0, 2])

    assert moved(2.0 + 0.35) < 0.5 * moved(2.0 - 0.35)


def _cloud(rng: np.random.Generator, m: int, spread_rad: float) -> ParticleFilter:
    layout = StateLayout(("r", "a", "b"), "r")
    pf = ParticleFilter(
        layout, m, (-5.0, 5.0, -5.0, 5.0), rng=rng, reinject_fraction=0.0, rotation_kernel=0.1
    )
    shape = np.array([3.0, 0.0, 0.0, 4.0]) + 0.02 * rng.standard_normal((m, 4))
    pf.particles = shape
    pf.rotate(
        rng.normal(0.3, spread_rad, m) if spread_rad < np.pi else rng.uniform(-np.pi, np.pi, m)
    )
    return pf


def _distances(pf: ParticleFilter) -> np.ndarray:
    rel = pf.particles[:, :4].reshape(-1, 2, 2)
    return np.stack(
        [
            np.linalg.norm(rel[:, 0], axis=1),
            np.linalg.norm(rel[:, 1], axis=1),
            np.linalg.norm(rel[:, 0] - rel[:, 1], axis=1),
        ]
    )


def test_orientation_kernel_keeps_ranges_mean_and_spread_and_renews_the_orientations() -> None:
    rng = np.random.default_rng(1)
    pf = _cloud(rng, 20_000, np.radians(3.0))
    # collapse onto 5 ancestors, as hitchhiking resampling does
    pf.particles = pf.particles[rng.integers(0, 5, pf.n)]
    ref = np.median(pf.particles[:, :4].reshape(-1, 2, 2), axis=0)

    def angles() -> np.ndarray:  # orientation relative to one fixed formation
        rel = pf.particles[:, :4].reshape(-1, 2, 2)
        return np.arctan2(
            rel[:, :, 1] @ ref[:, 0] - rel[:, :, 0] @ ref[:, 1],
            rel[:, :, 0] @ ref[:, 0] + rel[:, :, 1] @ ref[:, 1],
        )

    before_theta, before_d = angles(), _distances(pf)
    assert len(np.unique(np.round(before_theta, 9))) == 5
    assert pf.rejuvenate_rotation(0.1)
    after_theta = angles()
    np.testing.assert_allclose(_distances(pf), before_d, atol=1e-9)  # no range changes
    assert after_theta.mean() == pytest.approx(before_theta.mean(), abs=np.radians(0.05))
    assert after_theta.std() == pytest.approx(before_theta.std(), rel=0.05)
    assert len(np.unique(np.round(after_theta, 9))) > 10_000


def test_orientation_kernel_leaves_an_unresolved_bearing_alone() -> None:
    rng = np.random.default_rng(2)
    pf = _cloud(rng, 5_000, np.pi)  # orientations uniform: rotations compete, nothing to smooth
    before = pf.particles.copy()
    assert not pf.rejuvenate_rotation(0.1)
    np.testing.assert_array_equal(pf.particles, before)


def test_orientation_kernel_needs_a_formation() -> None:
    rng = np.random.default_rng(3)
    pf = ParticleFilter(
        StateLayout(("r", "a"), "r"), 2_000, (-5.0, 5.0, -5.0, 5.0), rng=rng, rotation_kernel=0.1
    )
    pf.particles = np.array([3.0, 0.0]) + 0.05 * rng.standard_normal((2_000, 2))
    assert not pf.rejuvenate_rotation(0.1)  # one relative position: its bearing is the state


def test_defaults_use_the_nlos_model_and_the_kernel() -> None:
    fc = FilterConfig()
    assert fc.likelihood.range_model == "nlos" and fc.resampling.rotation_kernel > 0.0
    with pytest.raises(ValueError):
        ParticleFilter(
            StateLayout(("r", "a"), "r"),
            10,
            (-1.0, 1.0, -1.0, 1.0),
            rng=np.random.default_rng(0),
            rotation_kernel=1.0,
        )


def test_an_online_bias_keeps_the_nlos_model_only_where_its_prior_is_a_calibration() -> None:
    """A calibrated pair's online bias is pinned near its line-of-sight peak: the NLOS-aware
    model; an uncalibrated one is confounded with the one-sided excess: the symmetric model."""
    from relloc.events import RangeEvent
    from relloc.filter.measurement import ModelContext
    from relloc.localizers.priors import bias_layout
    from relloc.simulator import multi_scenario

    config = multi_scenario(seed=0, duration=1.0).config
    config = config.with_filter(
        self_calibration=dataclasses.replace(config.filter.self_calibration, bias_mode="online")
    )
    calibrated = next(iter(config.uwb.pairs))
    uncalibrated = dataclasses.replace(
        config.uwb, pairs={k: v for k, v in config.uwb.pairs.items() if k != calibrated}
    )
    for uwb, nlos in ((config.uwb, True), (uncalibrated, False)):
        team = dataclasses.replace(config, uwb=uwb)
        layout, _ = bias_layout(team)
        a, b = calibrated.split("-")
        ra, rb = (next(r.name for r in team.robots if r.uwb_node == n) for n in (a, b))
        (model,) = RangeBatch.build(
            [RangeEvent(0.0, ra, rb, 3.0, a, b)], ModelContext(team, layout, range_model="nlos")
        )
        assert (model.nlos_fraction > 0.0) == nlos
