"""The sampled filter's online bias on a new session.

A single-range pair (the ``single`` scenario: ``r0`` static, ``r1`` circling, one range) whose
config carries no pair calibration, as on ``pair_range_20220907_1725``: ``--bias online`` must
not be worse than the default bias (``uwb.default_bias`` widened by ``default_bias_sigma``)
by more than 0.03 m, whatever the session's true bias and odometry scale error. The circle keeps
the pair's distance in a narrow band, so the data barely determine the bias: the online
estimate is only as good as its prior, which is why the sampled filter's prior has the
default's width.
Figures over seeds, biases and scale errors: docs/explanation/self-calibration.md, "Online bias on a new
session" (``scripts/online_bias_sessions.py``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from relloc.config import TeamConfig
from relloc.engine import Engine
from relloc.estimators.particle.localizer import ParticleFilterLocalizer
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.localizers.priors import bias_layout
from relloc.methods import build_pipeline
from relloc.simulator import Simulation, UwbErrorModel, single_scenario
from relloc.simulator.error_models import OdometryErrorModel


def _session(seed: int, bias: float, scale_error: float) -> tuple[Simulation, TeamConfig]:
    sim = single_scenario(
        seed,
        uwb=UwbErrorModel(bias_range=(bias, bias)),
        odometry=OdometryErrorModel(scale_range=(1.0 - scale_error, 1.0 - scale_error)),
    )
    config = replace(sim.config, uwb=replace(sim.config.uwb, pairs={})).with_filter(particles=3000)
    return sim, config


def _ape(
    sim: Simulation, config: TeamConfig, seed: int
) -> tuple[float, tuple[float, float] | None]:
    gt = GroundTruth(config.reference)
    engine = Engine([build_pipeline("pf", config, seed=seed)], truth_sinks=[gt.add])
    engine.run(sim.events())
    method = evaluate(engine, gt, "sim", 10.0).methods["pf"]
    return method.robots["r1"].median, next(iter(method.final_biases.values()), None)


def test_the_online_prior_of_an_uncalibrated_pair_is_the_default_bias_with_its_width() -> None:
    """Both modes believe the same about a pair nobody calibrated: ``default_bias`` +-
    ``default_bias_sigma``; the online mode only departs from it as far as the data say."""
    _, config = _session(0, 0.3, 0.0)
    config = replace(config, uwb=replace(config.uwb, default_bias=0.28, default_bias_sigma=0.12))
    localizer = ParticleFilterLocalizer(config.with_modes(bias="online"))
    assert localizer.layout.bias_pairs == ("n_0-n_1",)
    np.testing.assert_allclose(localizer.filter.extra_prior, [0.28, 0.12**2])
    # the Gaussian-sum filter keeps its own width (bias_prior_sigma_uncalibrated)
    _, prior = bias_layout(config.with_modes(bias="online"))
    assert prior.flat() == pytest.approx([0.28, 0.25**2])
    assert prior.latents == ()  # one range cannot tell a shared offset from the distance


@pytest.mark.parametrize(
    ("seed", "bias", "scale_error"),
    [(1, 0.3, 0.08), (0, 0.1, 0.0), (3, 0.5, 0.08)],
)
def test_online_bias_is_no_worse_than_the_default_on_a_new_session(
    seed: int, bias: float, scale_error: float
) -> None:
    """Filter seeds ``seed`` to ``seed + 2`` on the session: all but one and their mean no
    more than 0.03 m worse online. One seed says little: over seeds 0-7 of the first session
    the online bias is 0.002-0.003 m better on average, its worst seed 0.036 m worse with the
    NumPy step, 0.041 m with the compiled one."""
    sim, config = _session(seed, bias, scale_error)
    worse = []
    for run in (seed, seed + 1, seed + 2):
        default, _ = _ape(sim, config, run)
        online, belief = _ape(sim, config.with_modes(bias="online"), run)
        assert belief is not None
        worse.append(online - default)
    assert sum(w <= 0.03 for w in worse) >= 2 and np.mean(worse) <= 0.03, worse
