"""Splitting a Gaussian of the self-calibrating filter whose heading has grown wide
(:meth:`relloc.estimators.gaussian_sum.filter.GaussianSumFilter.split_headings`).

A robot that nobody sees and that sees nobody is dead reckoning: its heading's random walk
widens ``u`` tangentially, and its predicted position spreads along an arc (it drove some
metres in a direction known to +-20 deg, say). One Gaussian is a poor fit to an arc, and a
range linearised at its centre pulls the state the wrong way. With ``split_heading_std`` set,
after each prediction every Gaussian whose widest known heading has an angular std above it is
replaced by three, along that heading's tangent ``e`` in the full state: means ``mu + a_k s``
and covariance ``P - (1 - sigma^2) s s^T`` with ``s = P e / sqrt(e^T P e)`` (so the positions
correlated with the heading move with it), ``a = (-1.058, 0, 1.058)``, weights
``(0.225, 0.550, 0.225)``, ``sigma = 0.672``: the three-component split of a unit Gaussian
that keeps its mean and variance (the splitting library of Huber et al. and DeMars et al.).
The enlarged mixture is resampled back to ``M`` Gaussians, so the count and the cost per step
stay fixed. Range-only sightings are where this matters (docs/explanation/mrclam.md).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from relloc.filter.calibration import CalibrationLayout
from relloc.filter.resampling import systematic_resample

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

SPLIT_W = (0.2252246249, 0.5495507502, 0.2252246249)
SPLIT_MU = (-1.0575154615, 0.0, 1.0575154615)
SPLIT_SIGMA = 0.6715662887
"""The three-component split of a unit Gaussian that keeps its mean and variance: weights,
means and the components' standard deviation (module docstring)."""


def split_headings(
    layout: CalibrationLayout,
    mean: FloatArray,
    cov: FloatArray,
    logw: FloatArray,
    magnitude_done: BoolArray,
    max_std: float,
    rng: np.random.Generator,
) -> tuple[int, tuple[FloatArray, FloatArray, FloatArray, BoolArray] | None]:
    """Split every Gaussian (``mean`` ``(M, D)``, ``cov`` ``(M, D, D)``, log-weights, which
    ``|u|`` pseudo-measurements are done) whose widest known heading (angular std of ``u``:
    tangential std over ``|u|``) exceeds ``max_std`` (rad) into three along that heading, then
    resample the enlarged mixture back to ``M`` (systematic; equal weights). Returns how many
    were split and the new ``(mean, cov, logw, magnitude_done)`` (``None`` if none was)."""
    lay = layout
    n, width = mean.shape
    worst = np.zeros(n)
    direction = np.zeros((n, width))
    for robot in lay.robots:
        c0, c1 = lay.u_columns(robot)
        mu = mean[:, c0 : c1 + 1]
        norm = np.sqrt(np.sum(mu * mu, axis=1))
        t = np.stack([-mu[:, 1], mu[:, 0]], axis=1) / np.maximum(norm, 1e-9)[:, None]
        var_t = np.einsum("ma,mab,mb->m", t, cov[:, c0 : c1 + 1, c0 : c1 + 1], t)
        std = np.where(norm > 0.5, np.sqrt(np.maximum(var_t, 0.0)) / np.maximum(norm, 1e-9), 0.0)
        better = std > worst
        worst = np.where(better, std, worst)
        direction[better] = 0.0
        direction[better, c0] = t[better, 0]
        direction[better, c1] = t[better, 1]
    sel = np.flatnonzero(worst > max_std)
    if not sel.size:
        return 0, None
    e = direction[sel]
    pe = np.einsum("kde,ke->kd", cov[sel], e)
    sd = pe / np.sqrt(np.maximum(np.einsum("kd,kd->k", pe, e), 1e-18))[:, None]
    child_cov = cov[sel] - (1.0 - SPLIT_SIGMA**2) * sd[:, :, None] * sd[:, None, :]
    keep = np.setdiff1d(np.arange(n), sel)
    means = [mean[keep]] + [mean[sel] + mu_k * sd for mu_k in SPLIT_MU]
    covs = [cov[keep]] + [child_cov] * 3
    logws = [logw[keep]] + [logw[sel] + math.log(w_k) for w_k in SPLIT_W]
    done = [magnitude_done[keep]] + [magnitude_done[sel]] * 3
    mean_all, cov_all = np.concatenate(means), np.concatenate(covs)
    logw_all, done_all = np.concatenate(logws), np.concatenate(done)
    w = np.exp(logw_all - logw_all.max())
    idx = systematic_resample(w / w.sum(), rng, n)
    return int(sel.size), (mean_all[idx], cov_all[idx], np.full(n, -math.log(n)), done_all[idx])
