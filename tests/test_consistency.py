"""Consistency figures: NEES and 95 % ellipse coverage of the published covariances, and the
shape APE after one alignment for the run."""

from __future__ import annotations

import math

import numpy as np
import pytest

from relloc.estimate import Estimate
from relloc.evaluation.consistency import CHI2_2D_95, consistency
from relloc.evaluation.gauges import associate_shapes
from relloc.evaluation.metrics import GroundTruth, align
from relloc.events import GroundTruthEvent


def _truth() -> GroundTruth:
    gt = GroundTruth("r0")
    for t in np.arange(0.0, 10.01, 0.5):
        gt.add(GroundTruthEvent(float(t), "r0", (1.0, 1.0)))
        gt.add(GroundTruthEvent(float(t), "r1", (3.0, 1.0)))  # r1 at (2, 0) relative to r0
        gt.add(GroundTruthEvent(float(t), "r2", (1.0, 2.0)))  # r2 at (0, 1)
    return gt


def test_nees_and_coverage_of_known_errors() -> None:
    # r1: error (0.3, 0) with variance 0.01 on x: NEES 9 (outside); then error 0.1: NEES 1.
    ests = [
        Estimate(
            float(t),
            "pf",
            "r0",
            {"r1": (2.0 + (0.3 if t < 5 else 0.1), 0.0)},
            {"r1": ((0.01, 0.0), (0.0, 0.04))},
        )
        for t in range(10)
    ]
    c = consistency(ests, _truth(), ["r1"], t_start=2.0)["r1"]
    np.testing.assert_allclose(c.nees, [9.0] * 3 + [1.0] * 5)
    assert c.coverage == pytest.approx(5 / 8)
    assert c.nees_median == pytest.approx(1.0)
    assert 1.0 < CHI2_2D_95 < 9.0
    # Estimates without covariances (multilateration) give no figure.
    assert consistency([Estimate(3.0, "m", "r0", {"r1": (2.0, 0.0)})], _truth(), ["r1"], 0.0) == {}


def test_shape_ape_fits_one_rotation_and_reflection_for_the_run() -> None:
    # The published shape: the true formation mirrored and turned by 1 rad, as a gauge would.
    c, s = math.cos(1.0), math.sin(1.0)

    def turned(x: float, y: float) -> tuple[float, float]:
        return (c * x + s * y, s * x - c * y)  # mirror y, then rotate

    ests = [
        Estimate(
            float(t),
            "pf",
            "r0",
            {"r1": (0.0, 0.0), "r2": (0.0, 0.0)},
            orientation_observable=False,
            shape={"r1": turned(2.0, 0.0), "r2": turned(0.0, 1.0)},
            shape_gauge="r1",
        )
        for t in range(10)
    ]
    shaped = align(associate_shapes(ests, _truth(), ["r1", "r2"]), "run")
    for p in shaped.values():
        np.testing.assert_allclose(p.errors, 0.0, atol=1e-9)


def test_run_aligned_ape_removes_one_rotation_for_every_method() -> None:
    from relloc.evaluation.aligned_scores import RunAlignedApe
    from relloc.evaluation.metric import MethodRun
    from relloc.evaluation.metrics import associate
    from relloc.evaluation.scores import Ape

    # A filter whose formation is right but turned by 0.1 rad, with 0.05 m of noise on r1.
    c, s = math.cos(0.1), math.sin(0.1)
    ests = [
        Estimate(float(t), "pf", "r0", {"r1": (2.0 * c + 0.05 * (-1) ** t, 2.0 * s), "r2": (-s, c)})
        for t in range(10)
    ]
    truth = _truth()
    paired = associate(ests, truth, ["r1", "r2"])
    run = MethodRun("pf", ests, truth, ["r1", "r2"], 0.0, 2.0, paired)
    aligned = RunAlignedApe().compute(run).stats
    raw = Ape().compute(run).stats
    assert raw["r1"].median == pytest.approx(math.hypot(2 * c - 2, 2 * s), abs=0.05)
    assert aligned["r1"].median == pytest.approx(0.05, abs=0.01)
    assert aligned["r2"].median < 0.02 < raw["r2"].median
    # Multilateration's own run alignment is kept; the per-step oracle gets no figure.
    assert (
        RunAlignedApe().compute(MethodRun("m", ests, truth, ["r1"], 0.0, 2.0, paired, "step")).stats
        == {}
    )


def test_step_aligned_ape_removes_a_rotation_at_every_estimate_and_scores_shapes() -> None:
    from relloc.evaluation.aligned_scores import RunAlignedApe, StepAlignedApe
    from relloc.evaluation.metric import MethodRun
    from relloc.evaluation.metrics import associate

    # A formation that is right but whose gauge turns by a new angle at every estimate: the run
    # alignment cannot remove that, the step alignment does.
    ests = []
    for t in range(6):
        c, s = math.cos(0.3 * t), math.sin(0.3 * t)
        ests.append(Estimate(float(t), "pf", "r0", {"r1": (2.0 * c, 2.0 * s), "r2": (-s, c)}))
    # ... and, while the orientation is unobservable, ring moments at the origin with the shape
    # in its gauge (the step alignment reads the shape there).
    hidden = [
        Estimate(
            float(t),
            "pf",
            "r0",
            {"r1": (0.0, 0.0), "r2": (0.0, 0.0)},
            orientation_observable=False,
            shape={"r1": (2.0, 0.0), "r2": (0.0, -1.0)},
        )
        for t in range(6, 10)
    ]
    truth = _truth()
    every = ests + hidden
    paired = associate(every, truth, ["r1", "r2"])
    run = MethodRun("pf", every, truth, ["r1", "r2"], 0.0, 2.0, paired)
    step = StepAlignedApe().compute(run).stats
    assert step["r1"].n == step["r2"].n == 8  # 4 positions after the warm-up, 4 shapes
    assert step["r1"].max < 1e-9 and step["r2"].max < 1e-9
    assert RunAlignedApe().compute(run).stats["r1"].median > 0.5
    # an aligned method (multilateration and its oracle) gets no figure
    assert (
        StepAlignedApe()
        .compute(MethodRun("m", every, truth, ["r1"], 0.0, 2.0, paired, "run"))
        .stats
        == {}
    )
