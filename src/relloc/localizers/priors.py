"""What every estimator kind starts from and publishes at least: the prior of the online pair
biases (one belief per UWB node pair, offsets they share: :func:`bias_layout`,
:class:`BiasPrior`), the covariance a published estimate keeps per axis
(:func:`covariance_floor`) and about the formation's rotation (``ROTATION_FLOOR``,
:func:`with_rotation_floor`). Shared by the kinds of :mod:`relloc.estimators`, so that one kind
never imports another's localizer for them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.events import pair_key
from relloc.filter.state import StateLayout

BIAS_PRIOR_SIGMA = 0.05
"""Online biases: prior standard deviation (m) of a calibrated pair's bias about its
calibration (the spread of the pair biases between sessions)."""
BIAS_PRIOR_SIGMA_UNCALIBRATED = 0.25
"""Online biases in the Gaussian-sum filter (headings or scales estimated as well): prior
standard deviation (m) of an uncalibrated pair's bias. The sampled filter uses
``uwb.default_bias_sigma`` instead, the width its default mode assumes for the same pair: a
wider prior let the bias run, on a new session, along what one range cannot tell apart (a
longer bias, a nearer robot) (docs/explanation/self-calibration.md, "Online bias on a new session")."""


FloatArray = NDArray[np.float64]


class BiasPosterior(Protocol):
    """What a smoother's window says of the online biases (its latest estimates)."""

    biases: FloatArray

    def offset_estimates(self) -> tuple[list[float], list[float]]: ...

    def bias_joint(self) -> FloatArray: ...


@dataclass(frozen=True)
class BiasPrior:
    """The prior of the online pair biases: ``b = mean + A v + d``. ``v`` are shared latent
    offsets, each ``N(0, latent_sigma^2)``: the team's (one hardware delay every uncalibrated
    pair shares) and each node's (a transceiver's delay, in every pair it is in); ``A`` says
    which pair shares which. ``d_j`` is the pair's own deviation, ``N(0, sigma_j^2)``. A
    calibrated pair shares no team offset (its calibration holds it), but its nodes' offsets:
    what moved since the calibration. The shared offsets' evidence is the team's: an offset
    common to many ranges is not what a change of the formation makes of them
    (docs/explanation/bias-offsets.md)."""

    pairs: tuple[str, ...]
    mean: FloatArray
    sigma: FloatArray
    """Each pair's own deviation std ``(B,)``."""
    latents: tuple[str, ...]
    """The shared offsets' names (``"team"``, the node ids)."""
    loading: FloatArray
    """``A`` ``(B, L)``: 1 where pair ``j`` shares offset ``l``."""
    latent_sigma: FloatArray
    """Each shared offset's prior std ``(L,)``."""
    latent_mean: FloatArray | None = None
    """Each shared offset's prior mean ``(L,)`` (``None``: 0; a carried posterior has one)."""

    @property
    def offset_mean(self) -> FloatArray:
        """Each shared offset's prior mean ``(L,)``."""
        return np.zeros(self.latent_sigma.size) if self.latent_mean is None else self.latent_mean

    @property
    def marginal_mean(self) -> FloatArray:
        """Each bias's prior mean ``(B,)``: ``mean + A offset_mean``."""
        return self.mean + self.loading @ self.offset_mean

    def carried(self, biases: FloatArray, offsets: FloatArray, joint: FloatArray) -> BiasPrior:
        """The posterior of the biases ``(B,)`` and shared offsets ``(L,)`` with their joint
        covariance ``(B + L, B + L)`` as the prior of a restart, so that what the run taught is
        not forgotten: each offset at its estimate, each pair's deviation ``b - A v`` at its
        estimate, with their marginal stds (their correlations dropped)."""
        nb = self.mean.size
        pick = np.hstack([np.eye(nb), -self.loading])  # d + mean = b - A v
        dev_var = np.einsum("ij,jk,ik->i", pick, joint, pick)
        off_var = np.diag(joint)[nb:]
        return BiasPrior(
            self.pairs,
            biases - self.loading @ offsets,
            np.sqrt(np.maximum(dev_var, 1e-12)),
            self.latents,
            self.loading,
            np.sqrt(np.maximum(off_var, 1e-12)),
            np.asarray(offsets, float),
        )

    def carried_from(self, window: BiasPosterior) -> BiasPrior | None:
        """:meth:`carried` of a smoother ``window``'s posterior (its biases, shared offsets and
        their joint covariance); ``None`` where there are no online biases or that posterior
        cannot be had (the graph that failed)."""
        if not self.pairs:
            return None
        try:
            offsets = np.array(window.offset_estimates()[0], float)
            joint = window.bias_joint()
        except (RuntimeError, ValueError, np.linalg.LinAlgError):
            return None
        if not np.all(np.isfinite(joint)):
            return None
        return self.carried(window.biases, offsets, joint)

    @property
    def covariance(self) -> FloatArray:
        """The biases' joint prior covariance ``(B, B)``."""
        a = self.loading * self.latent_sigma
        return np.diag(self.sigma**2) + a @ a.T

    @property
    def variance(self) -> FloatArray:
        """Each bias's marginal prior variance ``(B,)``."""
        return self.sigma**2 + (self.loading * self.latent_sigma) ** 2 @ np.ones(
            self.latent_sigma.size
        )

    def flat(self) -> list[float]:
        """(mean, marginal variance) per pair, the columns of a belief at the prior."""
        out = np.empty(2 * self.mean.size)
        out[0::2], out[1::2] = self.marginal_mean, self.variance
        return out.tolist()

    def beliefs(self, rng: np.random.Generator, m: int) -> FloatArray:
        """``m`` draws of the Rao-Blackwellised beliefs ``(m, 2B)``: each draws the shared
        offsets; its beliefs are the pairs' own deviations about them (mean, variance)."""
        out = np.empty((m, 2 * self.mean.size))
        v = rng.standard_normal((m, self.latent_sigma.size)) * self.latent_sigma
        out[:, 0::2] = self.mean + (self.offset_mean + v) @ self.loading.T
        out[:, 1::2] = self.sigma**2
        return out


def bias_layout(
    config: TeamConfig,
    *,
    uncalibrated_sigma: float | None = None,
    team: bool = True,
    nodes: bool = True,
) -> tuple[StateLayout, BiasPrior]:
    """The sampled state's layout and the prior of its online pair biases (none unless
    ``bias_mode = "online"``). An uncalibrated pair's prior is ``uwb.default_bias`` plus the
    team offset (``uwb.team_offset_sigma``) plus its own deviation of ``uncalibrated_sigma``
    (default: ``BIAS_PRIOR_SIGMA_UNCALIBRATED``); a calibrated pair's its bias +- its stated
    ``bias_sigma`` (default ``BIAS_PRIOR_SIGMA``); every pair its nodes' offsets
    (``uwb.node_offset_sigma``). ``team``/``nodes`` false leave those offsets out (a pair with
    none is its own deviation's prior alone), as does a team whose pairs are no more than the
    shape's ``2N - 3`` degrees of freedom (two robots, one range: an offset is a distance)."""
    fc = config.filter
    names = config.robot_names
    node_pairs: list[str] = []
    if fc.self_calibration.bias_mode == "online":
        node_pairs = sorted(
            {
                pair
                for i, a in enumerate(names)
                for b in names[i + 1 :]
                for pair in _node_pairs(config, a, b)
            }
        )
    own = BIAS_PRIOR_SIGMA_UNCALIBRATED if uncalibrated_sigma is None else uncalibrated_sigma
    uwb = config.uwb
    node_ids = sorted({n for p in node_pairs for n in p.split("-")})
    latents = ["team", *node_ids]
    latent_sigma = np.array(
        [uwb.team_offset_sigma if team else 0.0]
        + [uwb.node_offset_sigma if nodes else 0.0] * len(node_ids)
    )
    loading = np.zeros((len(node_pairs), len(latents)))
    mean, sigma = [], []
    for j, pair in enumerate(node_pairs):
        cal = uwb.pairs.get(pair)
        if cal is not None:
            mean.append(cal.bias)
            sigma.append(BIAS_PRIOR_SIGMA if cal.bias_sigma is None else cal.bias_sigma)
        else:
            mean.append(uwb.default_bias)
            sigma.append(own)
            loading[j, 0] = 1.0
        for node in pair.split("-"):
            loading[j, latents.index(node)] = 1.0
    if len(node_pairs) <= 2 * len(names) - 3:
        latent_sigma[:] = 0.0  # ranges that do not over-determine the shape cannot tell an offset
    keep = (latent_sigma > 0.0) & loading.any(axis=0)
    prior = BiasPrior(
        tuple(node_pairs),
        np.array(mean, float),
        np.array(sigma, float),
        tuple(lat for lat, k in zip(latents, keep, strict=True) if k),
        loading[:, keep],
        latent_sigma[keep],
    )
    return StateLayout(names, config.reference, tuple(node_pairs)), prior


def _node_pairs(config: TeamConfig, robot_a: str, robot_b: str) -> list[str]:
    """Keys of the UWB transceiver pairs between two robots' tags (robot names if no nodes)."""
    a = config.robot(robot_a).nodes or (robot_a,)
    b = config.robot(robot_b).nodes or (robot_b,)
    return [pair_key(x, y) for x in a for y in b]


ROTATION_FLOOR = 0.05
"""Std (rad) of the formation's rotation that the published covariance keeps once the
orientation is resolved: a range error that follows the robots' headings (an antenna pattern)
turns the apparent motion of every robot alike, about its amplitude over the robots' turning
radius (docs/explanation/scaling.md: 2.5-3 degrees on the grid), which no fusion of ranges and odometry
can tell from a turn of the formation."""


def with_rotation_floor(mean: FloatArray, cov: FloatArray, std: float) -> FloatArray:
    """``cov`` ``(K, 2, 2)`` plus a turn of the whole formation about the reference of ``std``
    rad: ``std^2 J J^T`` per robot, ``J = (-y, x)`` the derivative of its position ``mean``
    ``(K, 2)`` by the turn (:data:`ROTATION_FLOOR` says why a published covariance keeps one)."""
    x, y = mean[:, 0], mean[:, 1]
    turn = np.stack([np.stack([y * y, -x * y], axis=1), np.stack([-x * y, x * x], axis=1)], axis=1)
    return cov + std**2 * turn


def covariance_floor(config: TeamConfig, range_model: str) -> float:
    """Variance (m^2) per axis the filter adds to what it publishes: one range's noise under
    the localizer's range model (``[uwb] los_sigma``, or ``sigma`` for the symmetric model).
    Range errors are correlated in time, so fusing many cannot average them below that
    (:mod:`relloc.filter.summary`)."""
    sigma = config.uwb.los_sigma if range_model == "nlos" else config.uwb.sigma
    return float(sigma) ** 2
