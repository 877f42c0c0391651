"""The estimate's frame: body-frame moments of the Gaussian-sum filter, their scoring, their name."""

from __future__ import annotations

import math

import numpy as np
import pytest

from relloc.estimate import BODY_FRAME, Estimate
from relloc.evaluation.metrics import GroundTruth, truth_in_frame
from relloc.events import GroundTruthEvent
from relloc.filter.calibration import to_body_frame


def test_body_frame_moments_match_sampling_the_gaussian() -> None:
    """One Gaussian over two positions and the reference's heading vector: the linearised body
    frame mean and covariance agree with 200 000 exact transforms of samples of it, the
    correlation of position and heading included."""
    rng = np.random.default_rng(0)
    k = 2
    mean = np.array([3.0, 1.0, -1.0, 2.0, math.cos(0.4), math.sin(0.4)])
    a = rng.normal(size=(6, 6)) * 0.05
    cov = a @ a.T + np.diag([0.02, 0.02, 0.03, 0.01, 0.002, 0.002])
    yaw = 0.7
    body, body_cov = to_body_frame(mean[None], cov[None], k, (4, 5), yaw)
    x = rng.multivariate_normal(mean, cov, size=200_000)
    angle = yaw + np.arctan2(x[:, 5], x[:, 4])
    c, s = np.cos(angle), np.sin(angle)
    for j in range(k):
        px, py = x[:, 2 * j], x[:, 2 * j + 1]
        exact = np.stack([c * px + s * py, -s * px + c * py], -1)
        np.testing.assert_allclose(body[0, j], exact.mean(axis=0), atol=0.03)
        np.testing.assert_allclose(body_cov[0, j], np.cov(exact.T), rtol=0.1, atol=2e-3)


def test_a_body_frame_estimate_is_scored_against_the_truth_seen_from_the_reference() -> None:
    gt = GroundTruth("a")
    gt.add(GroundTruthEvent(0.0, "a", (1.0, 1.0), math.pi / 2))  # facing +y
    gt.add(GroundTruthEvent(0.0, "b", (1.0, 3.0), 0.0))  # 2 m ahead of a
    est = Estimate(0.0, "pf", "a", {"b": (2.0, 0.0)}, frame=BODY_FRAME)
    assert truth_in_frame(est, gt, "b") == pytest.approx((2.0, 0.0))
    heading = Estimate(0.0, "pf", "a", {"b": (0.0, 2.0)})
    assert truth_in_frame(heading, gt, "b") == pytest.approx((0.0, 2.0))
    assert (est.frame_id, heading.frame_id) == ("a/base_link", "a")
