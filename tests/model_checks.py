"""The Jacobian check every measurement model passes (navlie's): its rows' Gaussian densities sum
to its log-likelihood, and their gradient ``sum r h / var`` matches central finite differences."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray


def assert_rows_are_the_log_likelihood_and_its_gradient(
    model: Any, layout: Any, x: NDArray[np.float64]
) -> None:
    """Check ``model``'s rows at the states ``x`` (``(M, layout.width)``) of ``layout``."""
    ll = model.log_likelihood(layout.positions(x), x)
    grad = np.zeros_like(x)
    dens = np.zeros(x.shape[0])
    for k in range(model.rows):
        row = model.row(k, x)
        logd, inlier = row.density(row.residual, np.full(x.shape[0], row.variance))
        dens += logd
        grad[:, row.columns] += (inlier * row.residual / row.variance)[:, None] * row.jacobian
    np.testing.assert_allclose(dens, ll, rtol=1e-12)
    h = 1e-6
    for c in range(layout.width):
        up, down = x.copy(), x.copy()
        up[:, c] += h
        down[:, c] -= h
        fd = (
            model.log_likelihood(layout.positions(up), up)
            - model.log_likelihood(layout.positions(down), down)
        ) / (2 * h)
        np.testing.assert_allclose(grad[:, c], fd, rtol=1e-5, atol=1e-6)
