"""The smoother's custom factor (a range with an online bias, ``|p_a - p_b| + b - z``): its
Jacobians equal GTSAM's numerical derivative of its error, at generic points and where the
two positions nearly coincide."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import (
    numericalDerivative31,
    numericalDerivative32,
    numericalDerivative33,
)

from relloc.estimators.smoother.graph import _biased_range

MEASURED = 2.5
KEYS = [gtsam.symbol("x", 0), gtsam.symbol("x", 1), gtsam.symbol("b", 0)]
FACTOR = gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, 0.1), KEYS, _biased_range(MEASURED))


def _values(pa: np.ndarray, pb: np.ndarray, bias: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(KEYS[0], np.asarray(pa, float))
    values.insert(KEYS[1], np.asarray(pb, float))
    values.insert(KEYS[2], np.asarray(bias, float))
    return values


def _error(pa: np.ndarray, pb: np.ndarray, bias: np.ndarray) -> np.ndarray:
    return np.asarray(_biased_range(MEASURED)(FACTOR, _values(pa, pb, bias), None))


@pytest.mark.parametrize(
    ("pa", "pb", "bias"),
    [
        ((1.0, 2.0), (-0.5, 0.3), 0.2),
        ((3.0, -1.0), (2.0, 4.0), -0.1),
        ((0.1, 0.1), (0.1, 0.1 + 1e-3), 0.3),
    ],
)
def test_the_biased_range_jacobians_match_a_numerical_derivative(
    pa: tuple[float, float], pb: tuple[float, float], bias: float
) -> None:
    a, b, c = np.array(pa), np.array(pb), np.array([bias])
    jacobians: list[np.ndarray | None] = [None, None, None]
    error = _biased_range(MEASURED)(FACTOR, _values(a, b, c), jacobians)
    assert error[0] == pytest.approx(np.hypot(*(a - b)) + bias - MEASURED)
    numeric = [
        numericalDerivative31(_error, a, b, c, 1e-6),
        numericalDerivative32(_error, a, b, c, 1e-6),
        numericalDerivative33(_error, a, b, c, 1e-6),
    ]
    for analytic, expected, dim in zip(jacobians, numeric, (2, 2, 1), strict=True):
        assert analytic is not None and analytic.shape == (1, dim)
        assert np.allclose(analytic, expected, atol=1e-5)
