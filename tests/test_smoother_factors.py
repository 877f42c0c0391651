"""The smoother's custom factor (a range with an online bias, ``|p_a - p_b| + b - z``): its
Jacobians equal a central numerical derivative of its error, at generic points and where the
two positions nearly coincide."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from relloc.estimators.smoother.graph import _biased_range

STEP = 1e-6


def _error(values: gtsam.Values, factor: gtsam.CustomFactor, measured: float) -> float:
    return float(_biased_range(measured)(factor, values, None)[0])


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
    ka, kb, kbias = gtsam.symbol("x", 0), gtsam.symbol("x", 1), gtsam.symbol("b", 0)
    noise = gtsam.noiseModel.Isotropic.Sigma(1, 0.1)
    measured = 2.5
    factor = gtsam.CustomFactor(noise, [ka, kb, kbias], _biased_range(measured))
    values = gtsam.Values()
    values.insert(ka, np.array(pa))
    values.insert(kb, np.array(pb))
    values.insert(kbias, np.array([bias]))
    jacobians: list[np.ndarray | None] = [None, None, None]
    error = _biased_range(measured)(factor, values, jacobians)
    assert error[0] == pytest.approx(np.hypot(*np.subtract(pa, pb)) + bias - measured)
    for key, jacobian, dim in (
        (ka, jacobians[0], 2),
        (kb, jacobians[1], 2),
        (kbias, jacobians[2], 1),
    ):
        assert jacobian is not None and jacobian.shape == (1, dim)
        numeric = np.zeros((1, dim))
        for i in range(dim):
            for sign in (1.0, -1.0):
                moved = gtsam.Values(values)
                delta = np.zeros(dim)
                delta[i] = sign * STEP
                if dim == 2:
                    moved.update(key, values.atPoint2(key) + delta)
                else:
                    moved.update(key, values.atVector(key) + delta)
                numeric[0, i] += sign * _error(moved, factor, measured) / (2 * STEP)
        assert np.allclose(jacobian, numeric, atol=1e-5)
