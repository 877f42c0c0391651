"""The learned range correction checks itself: a correction that hurts is switched off from
the filter's own estimates, an input outside the training support falls back to the constant."""

from __future__ import annotations

import math

import numpy as np
import pytest

from relloc.engine import Engine, Pipeline
from relloc.estimators.particle.localizer import ParticleFilterLocalizer
from relloc.events import RangeEvent
from relloc.ranging.support import InputSupport
from relloc.simulator import multi_scenario
from relloc.stages.range_correction import RangeCorrector

BAD = "n_1-n_3"


class FixedModel:
    """A pair model that always predicts ``residual`` (duck-typed :class:`PairModel`)."""

    def __init__(
        self, pair: str, offset: float, residual: float, support: InputSupport | None = None
    ) -> None:
        self.pair, self.nodes, self.n_steps = pair, tuple(pair.split("-")), 1
        self.offset, self.residual = offset, residual
        self.residual_min, self.residual_max = -1.0, 1.0
        self.fallback, self.fallback_sigma, self.support, self.sigma = False, 0.1, support, 0.15

    def predict_raw(self, windows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = len(windows)
        return np.full(n, self.residual), np.full(n, self.sigma)


def _run(
    duration: float, bad_residual: float, seed: int = 0
) -> tuple[RangeCorrector, float, dict[str, float]]:
    """The five simulated robots through a corrector whose models add ``-bad_residual`` to
    ``BAD``'s ranges (the others exact): the corrector, when ``BAD`` was switched off (stream
    seconds after the first range, nan if never), and when any other pair was."""
    sim = multi_scenario(seed=seed, duration=duration)
    config = sim.config
    pairs = {
        RangeEvent(0, "", "", 0, a.uwb_node, b.uwb_node).node_pair
        for a in config.robots
        for b in config.robots
        if a.name < b.name
    }
    models = {
        p: FixedModel(
            p, config.uwb.calibration(*p.split("-"))[0], bad_residual if p == BAD else 0.0
        )
        for p in pairs
    }
    corrector = RangeCorrector.from_config(config, models)
    engine = Engine([Pipeline("pf_ul", ParticleFilterLocalizer(config, seed=seed), [corrector])])
    first, switched = math.nan, {}
    for event in sim.events():
        engine.feed(event)
        if isinstance(event, RangeEvent) and math.isnan(first):
            first = event.t
        for pair in corrector.check.off_pairs:
            switched.setdefault(pair, event.t - first)
    return corrector, switched.pop(BAD, math.nan), switched


@pytest.mark.parametrize(("seed", "residual"), [(0, -0.3), (1, 0.3)])
def test_a_correction_that_adds_a_bias_is_switched_off_within_ten_seconds(
    seed: int, residual: float
) -> None:
    corrector, when, others = _run(30.0, residual, seed)
    assert when <= 10.0, when  # measured 2.8-5.1 s over seeds 0-3 and both signs
    assert others == {}
    assert corrector.stats[f"correction_off.{BAD}"] == 1
    assert corrector.stats["checked_off"] > 0


def test_exact_corrections_stay_on() -> None:
    corrector, when, others = _run(20.0, bad_residual=0.0)
    assert math.isnan(when) and others == {}
    assert corrector.stats["checked_off"] == 0 and corrector.stats["corrected"] > 0


def test_an_input_outside_the_training_support_falls_back_to_the_constant() -> None:
    rng = np.random.default_rng(0)
    windows = np.stack(
        [
            np.column_stack(
                [
                    2.0 + 0.01 * np.arange(5) + rng.normal(0, 0.01, 5),
                    np.full(5, 0.1),
                    np.full(5, -0.2),
                ]
            )
            for _ in range(50)
        ]
    )
    support = InputSupport.of(windows)
    assert support.contains(windows).all()
    far = windows[:1].copy()
    far[0, :, 0] += 3.0  # ranges never seen in training
    turned = windows[:1].copy()
    turned[0, :, 1] += math.pi  # a relative heading never seen
    assert not support.contains(far)[0] and not support.contains(turned)[0]
    assert InputSupport.from_json(support.to_json()) == support

    model = FixedModel(
        "n_0-n_1", offset=0.2, residual=0.1, support=InputSupport.of(windows[:, -1:, :])
    )
    corrector = RangeCorrector(
        {"n_0-n_1": model}, yaw_provider=lambda robot, t: 0.1 if robot == "a" else -0.2
    )  # type: ignore[dict-item]
    inside = corrector.correct(RangeEvent(1.0, "a", "b", 2.02, "n_0", "n_1"))
    outside = corrector.correct(RangeEvent(2.0, "a", "b", 6.0, "n_0", "n_1"))
    assert inside.distance == 2.02 - 0.2 - 0.1
    assert outside.distance == 6.0 - 0.2 and outside.sigma == 0.1
    assert corrector.stats["out_of_support"] == 1 and corrector.stats["corrected"] == 1
