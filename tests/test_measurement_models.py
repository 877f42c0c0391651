"""The measurement-model protocol: a sensor from outside the package fuses in both filters and
through a localizer, and every registered model's linearisation agrees with its likelihood."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from model_checks import assert_rows_are_the_log_likelihood_and_its_gradient

from relloc.config import TeamConfig
from relloc.estimators.gaussian_sum.filter import CalibrationLayout, GaussianSumFilter
from relloc.estimators.particle.filter import ParticleFilter
from relloc.estimators.particle.localizer import ParticleFilterLocalizer
from relloc.events import GroundTruthEvent, RangeEvent, RelativeObservation, SightingEvent
from relloc.filter.measurement import (
    LinearRow,
    MeasurementModel,
    ModelContext,
    ValidationContext,
    finite,
)
from relloc.filter.registry import MODELS, register, unregister
from relloc.filter.state import StateLayout
from relloc.simulator import single_scenario


# ---------------------------------------------------------------------------- a toy sensor
@dataclass(frozen=True)
class XFix:
    """A 1-D position fix: ``robot``'s x relative to the reference, in the shared frame."""

    t: float
    robot: str
    x: float
    sigma: float


@dataclass(frozen=True)
class XFixModel:
    """Gaussian fixes of relative x coordinates: one model class, one registry entry."""

    events: ClassVar[tuple[type, ...]] = (XFix,)
    stat: ClassVar[str] = "x_fix"
    invariant: ClassVar[bool] = False
    needs_shared_heading: ClassVar[bool] = True
    conditions: ClassVar[bool] = False

    index: np.ndarray
    x: np.ndarray
    sigma: np.ndarray
    layout: object

    @classmethod
    def build(cls, events: Sequence[XFix], context: ModelContext) -> list[MeasurementModel]:
        lay = context.layout
        return [
            cls(
                np.array([lay.index(e.robot) for e in events]),
                np.array([e.x for e in events]),
                np.array([e.sigma for e in events]),
                lay,
            )
        ]

    @classmethod
    def rejection(cls, event: XFix, context: ValidationContext) -> str | None:
        if event.robot not in context.layout.robots or event.robot == context.layout.reference:
            return "unknown_robot"
        if not (finite(event.x) and finite(event.sigma)) or event.sigma <= 0.0:
            return "invalid_x_fix"
        return "late_measurement" if context.is_late(event.t) else None

    def log_likelihood(self, positions: np.ndarray, particles: np.ndarray) -> np.ndarray:
        r = self.x[:, None] - positions[0, self.index]
        s = self.sigma[:, None]
        return (-0.5 * (r / s) ** 2 - np.log(s) - 0.5 * math.log(2 * math.pi)).sum(axis=0)

    @property
    def rows(self) -> int:
        return len(self.x)

    def row(self, k: int, mean: np.ndarray) -> LinearRow:
        col = 2 * self.layout.slot_of(int(self.index[k]))  # type: ignore[attr-defined]
        n = mean.shape[0]
        return LinearRow(
            np.array([col]), np.ones((n, 1)), self.x[k] - mean[:, col], float(self.sigma[k]) ** 2
        )

    def condition(self, positions: np.ndarray, particles: np.ndarray) -> None:
        """No sufficient statistics."""


@pytest.fixture
def x_fix() -> Iterator[type[XFixModel]]:
    register(XFixModel)
    yield XFixModel
    unregister(XFixModel)


def _config() -> TeamConfig:
    return single_scenario(seed=0, duration=1.0).config


def test_a_model_from_outside_the_package_pulls_the_particle_filter(x_fix) -> None:
    config = _config()
    layout = StateLayout(config.robot_names, config.reference)
    pf = ParticleFilter(layout, 20_000, (-4, 4, -4, 4), rng=np.random.default_rng(0))
    before = pf.estimate().mean[0]
    (model,) = x_fix.build([XFix(0.0, "r1", 2.5, 0.1)], ModelContext(config, layout))
    assert pf.update([model])
    after = pf.estimate()
    assert abs(before[0] - 2.5) > 1.0
    assert after.mean[0, 0] == pytest.approx(2.5, abs=0.02)
    assert math.sqrt(after.cov[0, 0, 0]) == pytest.approx(0.1, abs=0.02)


def test_a_model_from_outside_the_package_pulls_the_gaussian_sum_filter(x_fix) -> None:
    config = _config()
    layout = CalibrationLayout(config.robot_names, config.reference)
    gsf = GaussianSumFilter(
        layout, 50, (-4, 4, -4, 4), rng=np.random.default_rng(0), position_sigma=1.0
    )
    start, y = gsf.mean[:, 0].copy(), gsf.mean[:, 1].copy()
    (model,) = x_fix.build([XFix(0.0, "r1", 2.5, 0.1)], ModelContext(config, layout))
    assert gsf.update([model])
    # each Gaussian's x is the Kalman update of prior N(start, 1) by the fix N(2.5, 0.01)
    np.testing.assert_allclose(gsf.mean[:, 0], (0.01 * start + 1.0 * 2.5) / 1.01)
    est = gsf.estimate()
    assert est.mean[0, 0] == pytest.approx(2.5, abs=0.05)
    np.testing.assert_array_equal(gsf.mean[:, 1], y)  # an x fix says nothing about y
    assert np.all(np.abs(gsf.mean[:, 0] - 2.5) < np.abs(start - 2.5) + 1e-12)


def test_a_localizer_fuses_a_registered_sensor_without_knowing_it(x_fix) -> None:
    """The single-range team cannot tell the bearing of r1 from one range: x fixes of r1
    (from the simulated ground truth, 5 cm) pin its x coordinate."""
    sim = single_scenario(seed=0, duration=8.0)
    loc = ParticleFilterLocalizer(sim.config.with_filter(particles=3000), seed=0)
    truth: dict[str, GroundTruthEvent] = {}
    rng = np.random.default_rng(1)
    estimates, fixes = [], []
    for ev in sim.events():
        if isinstance(ev, GroundTruthEvent):
            truth[ev.robot] = ev
            if ev.robot == "r1" and "r0" in truth and len(fixes) < int(ev.t * 5):
                fix = XFix(
                    ev.t,
                    "r1",
                    ev.position[0] - truth["r0"].position[0] + rng.normal(0.0, 0.05),
                    0.05,
                )
                fixes.append(fix)
                estimates += loc.process(fix)
            continue
        estimates += loc.process(ev)
    estimates += loc.flush()
    assert loc.stats["x_fix"] == len(fixes) > 20 and not loc.rejected
    last, fix = estimates[-1], fixes[-1]
    assert last.positions["r1"][0] == pytest.approx(fix.x, abs=0.15)
    # The cloud's own spread (the published variance adds the filter's covariance floor).
    assert math.sqrt(last.covariances["r1"][0][0] - loc.filter.covariance_floor) < 0.1


# ---------------------------------------------------------------------------- linearisation
def _events(config: TeamConfig) -> dict[type, list[object]]:
    """Sample events for every built-in model: a model registered without a case here fails
    the linearisation test below."""
    return {
        RangeEvent: [
            RangeEvent(0.0, "r0", "r1", 3.1, "n_0", "n_1"),
            RangeEvent(0.0, "r1", "r2", 2.2, "n_1", "n_2"),
            RangeEvent(0.0, "r0", "r2", 4.0, corrected=True),
        ],
        RelativeObservation: [
            RelativeObservation(0.0, "r1", "r2", (1.0, -2.0), 0.2),
            RelativeObservation(0.0, "r2", "r0", (-0.5, 0.7), 0.3),
        ],
        SightingEvent: [
            SightingEvent(0.0, "r1", "r2", 2.0, 0.4, 0.1, 0.02),
            SightingEvent(0.0, "r0", "r1", None, -2.9, 0.1, 0.05),
            SightingEvent(0.0, "r2", "r0", 1.5, None, 0.2, 0.05),
        ],
    }


@pytest.mark.parametrize(("online", "heading"), [(False, False), (True, False), (False, True)])
def test_every_models_rows_are_the_gradient_of_its_log_likelihood(
    online: bool, heading: bool
) -> None:
    """navlie's Jacobian check: for the plain (outlier-free) models, the log-likelihood of a
    state is the sum of its rows' Gaussian densities, and its gradient ``sum r h / var`` (all
    columns, online bias columns included) matches central finite differences."""
    from relloc.simulator import multi_scenario

    config = multi_scenario(seed=0, duration=1.0).config
    names = config.robot_names[:3]
    config = TeamConfig(tuple(config.robot(n) for n in names), names[0], uwb=config.uwb)
    pairs = ("n_0-n_1", "n_0-n_2", "n_1-n_2") if online else ()
    layout = CalibrationLayout(names, names[0], bias_pairs=pairs, heading=heading)
    samples = _events(config)
    assert set(MODELS) <= set(samples), "give every registered model sample events here"
    rng = np.random.default_rng(0)
    x = rng.normal(0.0, 2.0, (4, layout.width))  # four states, one per row
    yaws = {"r0": 0.3, "r1": -2.0, "r2": 3.1}  # the observers' odometry yaws (sightings' bearings)
    context = ModelContext(
        config, layout, robust=False, range_model="symmetric", yaws=yaws, shared_heading=not heading
    )
    checked = 0
    for event_type, cls in MODELS.items():
        for model in cls.build(samples[event_type], context):
            assert_rows_are_the_log_likelihood_and_its_gradient(model, layout, x)
            checked += 1
    assert checked == len(MODELS)


def test_models_say_which_symmetries_they_keep_and_which_frame_they_need() -> None:
    assert MODELS[RangeEvent].invariant and not MODELS[RangeEvent].needs_shared_heading
    assert (
        not MODELS[RelativeObservation].invariant
        and MODELS[RelativeObservation].needs_shared_heading
    )


@pytest.mark.parametrize(("model_sigma", "expected"), [(None, 0.15), (0.05, 0.15), (0.4, 0.4)])
def test_a_corrected_ranges_own_sigma_only_widens_its_noise(
    model_sigma: float | None, expected: float
) -> None:
    """A learned correction's sigma (RangeEvent.sigma) makes an unsure range weigh less; a
    confident one never weighs more than the configured noise (sigma_uwb 0.15 m)."""
    from relloc.filter.ranges import RangeBatch

    config = _config()
    layout = StateLayout(config.robot_names, config.reference)
    events = [
        RangeEvent(0.0, "r0", "r1", 3.0, corrected=True, sigma=model_sigma),
        RangeEvent(0.05, "r0", "r1", 3.02, corrected=True, sigma=model_sigma),
    ]
    (model,) = RangeBatch.build(events, ModelContext(config, layout))
    assert isinstance(model, RangeBatch)
    assert model.sigma == pytest.approx([expected])
    assert model.nlos_fraction == 0.0  # corrected ranges keep the symmetric likelihood
