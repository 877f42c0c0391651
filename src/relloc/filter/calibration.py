"""The calibration state of the self-calibrating filter (:mod:`relloc.estimators.gaussian_sum.filter`):
which blocks are estimated and their columns (:class:`CalibrationLayout`), their noise and
priors (:class:`CalibrationNoise`), and the read-out of a heading from a mixture of Gaussians.

A robot's unknown odometry rotation and scale are one 2-vector ``u = s (cos theta, sin theta)``,
so that its displacement ``d`` moves it by ``A(d) u`` (:func:`rotation_jacobian`), linear in
``u``; a range is linear in its pair's bias.

The derivation: docs/explanation/internals.md, section ``relloc.filter.calibration``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import i0e, i1e

from relloc.filter.state import TeamLayout

FloatArray = NDArray[np.float64]


def rotation_jacobian(d: FloatArray) -> FloatArray:
    """``A(d)`` with ``A(d) u = s R(theta) d`` for ``u = s (cos theta, sin theta)``."""
    dx, dy = float(d[0]), float(d[1])
    return np.array([[dx, -dy], [dy, dx]])


@dataclass(frozen=True)
class CalibrationLayout(TeamLayout):
    """Which calibration blocks are estimated, and their state columns."""

    heading: bool = False
    """Estimate each non-reference robot's odometry-frame rotation (with its scale, as ``u``)."""
    scale: bool = False
    """Estimate odometry scales online (as ``|u|`` in heading mode, else as one scale column
    per robot)."""
    colored_bias: bool = True
    """Beside each online pair's constant bias, a zero-mean, time-correlated range error (a
    first-order Gauss-Markov process, :class:`CalibrationNoise` ``colored_sigma`` and
    ``colored_time``): one more column per pair, after the biases. It takes up the
    heading-dependent part of the UWB error (antenna pattern, body occlusion), which a white
    range noise cannot: without it that error moves the bias estimate (through its random
    walk) or the positions. The published bias is the constant part."""
    rates: tuple[str, ...] = ()
    """Heading mode: the robots whose odometry heading drifts at a constant rate held as a
    state (their gyro bias, rad/s; one last column each, in this order), which turns their
    ``u`` at every step (:class:`CalibrationNoise` ``rate_sigma``). A random walk follows a
    constant rate only with a lag, and a lagging reference turns every body-frame position."""

    @property
    def dim(self) -> int:
        """Position columns."""
        return 2 * self.n_others

    @property
    def u_start(self) -> int:
        return self.dim

    @property
    def scale_start(self) -> int:
        """First column after the heading vectors (one ``u`` per robot, the reference's last)."""
        return self.dim + (2 * len(self.robots) if self.heading else 0)

    @property
    def ref_scale_column(self) -> int:
        """Column of the reference robot's scale in compass mode with online scale (-1
        otherwise: fixed scales, or heading mode where it is ``|u_ref|``)."""
        if not self.scale or self.heading:
            return -1
        return self.scale_start + self.n_others

    @property
    def bias_start(self) -> int:
        n = self.scale_start
        if self.scale and not self.heading:
            n += 1 + self.n_others
        return n

    @property
    def colored_start(self) -> int:
        """First column of the time-correlated range errors (``colored_bias``)."""
        return self.bias_start + len(self.bias_pairs)

    @property
    def colored_end(self) -> int:
        """One past the last time-correlated range error column."""
        return self.colored_start + (len(self.bias_pairs) if self.colored_bias else 0)

    @property
    def rate_robots(self) -> tuple[str, ...]:
        """The robots with a drift-rate column (none outside heading mode)."""
        return self.rates if self.heading else ()

    def rate_column(self, robot: str) -> int:
        """Column of ``robot``'s heading drift rate (-1 without one)."""
        rates = self.rate_robots
        return self.colored_end + rates.index(robot) if robot in rates else -1

    @property
    def width(self) -> int:
        return self.colored_end + len(self.rate_robots)

    def u_columns(self, robot: str) -> tuple[int, int]:
        """Columns of ``robot``'s heading vector ``u`` (heading mode). The reference has one
        too: its prior is ``(1, 0)`` (its odometry frame *is* the shared frame), and its
        random walk follows the drift of its own odometry heading."""
        k = self.n_others if robot == self.reference else self.others.index(robot)
        return self.u_start + 2 * k, self.u_start + 2 * k + 1

    def scale_column(self, robot: str) -> int:
        """Column of ``robot``'s own scale in compass mode with online scale (-1 otherwise)."""
        if not self.scale or self.heading:
            return -1
        if robot == self.reference:
            return self.ref_scale_column
        return self.scale_start + self.others.index(robot)

    def bias_column(self, pair: str) -> int:
        return self.bias_start + self.bias_pairs.index(pair)

    def colored_column(self, pair: str) -> int:
        """Column of ``pair``'s time-correlated range error (-1 without ``colored_bias``)."""
        return self.colored_start + self.bias_pairs.index(pair) if self.colored_bias else -1

    def bias_state_columns(self, pair: str) -> tuple[int, ...]:
        """The pair's bias and, with ``colored_bias``, its time-correlated error: a range sees
        their sum."""
        if pair not in self.bias_pairs:
            return ()
        if self.colored_bias:
            return (self.bias_column(pair), self.colored_column(pair))
        return (self.bias_column(pair),)


@dataclass(frozen=True)
class CalibrationNoise:
    """Per-step noise and prior parameters of the calibration blocks."""

    heading_walk: float = 0.01
    """Random walk of each relative heading (rad per sqrt(s)): gyro drift."""
    reference_heading_walk: float = 0.003
    """Random walk of the reference robot's own odometry heading in the frame it defines (rad
    per sqrt(s)). Only the reference's motion against the ranges tells its drift, and only
    weakly: a smaller walk than the others' keeps the frame from wandering more than the
    odometry does."""
    scale_walk: float = 0.001
    """Random walk of each odometry scale (per sqrt(s))."""
    bias_walk: float = 0.01
    """Random walk of each online range bias (m per sqrt(s))."""
    colored_sigma: float = 0.05
    """Stationary standard deviation of a pair's time-correlated range error (m; layout
    ``colored_bias``), of the order of the heading-dependent UWB error."""
    colored_time: float = 10.0
    """Correlation time of that error (s): how long the headings of the two ends relative to
    the bearing between them take to change (a turn in place, a pass by the other robot)."""
    u_prior_sigma: float = math.sqrt(0.5)
    """Per-axis standard deviation of the heading vector ``u`` before any motion (its angle is
    then uniform, ``E|u|^2 = 1``)."""
    scale_prior_sigma: float = 0.15
    """Prior standard deviation of an odometry scale when estimated online."""
    scale_fixed_sigma: float = 0.02
    """How tightly ``|u|`` is held to the configured scale when scales are fixed."""
    scale_bounds: tuple[float, float] = (0.5, 1.5)
    """The physical interval of an odometry scale (``[filter.self_calibration] scale_min``,
    ``scale_max``): each Gaussian's scale is held inside it
    (:meth:`relloc.estimators.gaussian_sum.filter.GaussianSumFilter.constrain_scales`)."""
    rate_sigma: float = 0.002
    """Prior standard deviation of a heading drift rate (rad/s; layout ``rates``): a gyro
    bias of a few degrees a minute."""
    magnitude_gate: float = 0.25
    """Apply the ``|u|`` pseudo-measurement once the angular std of ``u`` is below this (rad)."""


def circular_heading(mu: FloatArray, block: FloatArray, w: FloatArray) -> tuple[float, float]:
    """Circular mean and circular standard deviation (rad) of a heading held as ``u ~ N(mu, P)``
    per Gaussian (``mu`` ``(M, 2)``, ``block`` ``P`` ``(M, 2, 2)``, normalised weights ``w``).

    Each Gaussian's angle has the mean resultant length of a Rice phase with signal ``|mu|``
    and the tangential noise of ``P`` (1 when well determined, 0 when ``u`` is still at its
    prior); the mixture's resultant is their weighted vector sum. The spread is
    ``sqrt(-2 ln R)``, capped at pi (no information).
    """
    a = np.sqrt(np.sum(mu * mu, axis=1))
    t = np.stack([-mu[:, 1], mu[:, 0]], axis=1) / np.maximum(a, 1e-12)[:, None]
    var_t = np.einsum("ma,mab,mb->m", t, block, t)
    nu2 = a * a / np.maximum(var_t, 1e-18)
    x = nu2 / 4.0
    rho = np.sqrt(np.pi / 8.0) * np.sqrt(nu2) * (i0e(x) + i1e(x))
    rho = np.clip(rho, 0.0, 1.0)
    angle = np.arctan2(mu[:, 1], mu[:, 0])
    cx = float(np.sum(w * rho * np.cos(angle)))
    cy = float(np.sum(w * rho * np.sin(angle)))
    r = math.hypot(cx, cy)
    mean = math.atan2(cy, cx)
    spread = math.pi if r <= math.exp(-0.5 * math.pi**2) else math.sqrt(-2.0 * math.log(r))
    return mean, min(spread, math.pi)


def calibration_prior(
    layout: CalibrationLayout,
    noise: CalibrationNoise,
    heading_prior: dict[str, tuple[float, float]],
    bias_mean: FloatArray,
    bias_var: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Mean and covariance of the non-position columns (block diagonal): the reference's
    ``u`` at ``(1, 0)``, the others' ``u`` uniform in angle (or around ``heading_prior``:
    robot -> (angle, sigma), rad), the scales around 1, the biases at ``bias_mean`` +-
    ``sqrt(bias_var)`` and the time-correlated errors at their stationary spread."""
    lay, nz = layout, noise
    d = lay.width - lay.dim
    mean, cov = np.zeros(d), np.zeros((d, d))
    off = lay.dim
    if lay.heading:
        c0, c1 = (c - off for c in lay.u_columns(lay.reference))
        mean[c0] = 1.0
        cov[c0, c0] = (nz.scale_prior_sigma if lay.scale else nz.scale_fixed_sigma) ** 2
        cov[c1, c1] = 1e-12  # the reference's odometry frame defines the shared frame
        for robot in lay.others:
            c0, c1 = (c - off for c in lay.u_columns(robot))
            if robot in heading_prior:
                angle, sigma = heading_prior[robot]
                mean[c0], mean[c1] = math.cos(angle), math.sin(angle)
                # angular sigma tangentially, the scale prior radially (so the |u|
                # pseudo-measurement is not applied again: see GaussianSumFilter._set_prior_rows)
                radial = nz.scale_prior_sigma if lay.scale else nz.scale_fixed_sigma
                t = np.array([-math.sin(angle), math.cos(angle)])
                r = np.array([math.cos(angle), math.sin(angle)])
                block = sigma**2 * np.outer(t, t) + radial**2 * np.outer(r, r)
                cov[c0 : c1 + 1, c0 : c1 + 1] = block
            else:
                cov[c0, c0] = cov[c1, c1] = nz.u_prior_sigma**2
    if lay.scale:
        for robot in lay.robots:
            c = lay.scale_column(robot)
            if c >= 0:
                mean[c - off] = 1.0
                cov[c - off, c - off] = nz.scale_prior_sigma**2
    for k in range(len(lay.bias_pairs)):
        c = lay.bias_start + k - off
        mean[c] = bias_mean[k]
        cov[c, c] = bias_var[k]
        if lay.colored_bias:
            c = lay.colored_start + k - off
            cov[c, c] = nz.colored_sigma**2  # zero mean, stationary
    for robot in lay.rate_robots:
        c = lay.rate_column(robot) - off
        cov[c, c] = nz.rate_sigma**2
    return mean, cov


def to_body_frame(
    mean: FloatArray, cov: FloatArray, n_others: int, u_cols: tuple[int, int], reference_yaw: float
) -> tuple[FloatArray, FloatArray]:
    """Each Gaussian's relative positions in the reference robot's *body* frame, with their
    covariances: ``b_j = R(-(yaw + angle(u_ref))) p_j``, ``yaw`` the reference's odometry yaw
    and ``u_ref`` (columns ``u_cols``) the drift of its odometry frame, linearised per Gaussian
    over its joint covariance of positions and ``u_ref`` (their correlation kept: the body frame
    is what sightings and ranges observe, the odometry frame's rotation is not).
    ``mean`` ``(M, D)``, ``cov`` ``(M, D, D)`` -> ``(M, n_others, 2)``, ``(M, n_others, 2, 2)``."""
    k = n_others
    cols = np.r_[0 : 2 * k, u_cols[0], u_cols[1]]
    m = mean[:, cols]
    sub = cov[:, cols[:, None], cols[None, :]]
    u = m[:, 2 * k :]
    n2 = np.maximum(np.einsum("ma,ma->m", u, u), 1e-12)
    angle = reference_yaw + np.arctan2(u[:, 1], u[:, 0])
    c, s = np.cos(angle), np.sin(angle)
    rot = np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)  # R(-angle), (M, 2, 2)
    p = m[:, : 2 * k].reshape(-1, k, 2)
    body = np.einsum("mab,mjb->mja", rot, p)
    d_angle = np.stack([-u[:, 1], u[:, 0]], -1) / n2[:, None]  # d angle / d u, (M, 2)
    jac = np.zeros((m.shape[0], k, 2, 2 * k + 2))
    for j in range(k):
        jac[:, j, :, 2 * j : 2 * j + 2] = rot
    # d b / d angle = -J b (J the quarter turn): (b_y, -b_x)
    turn = np.stack([body[..., 1], -body[..., 0]], -1)
    jac[:, :, :, 2 * k :] = turn[..., :, None] * d_angle[:, None, None, :]
    body_cov = np.einsum("mjad,mde,mjbe->mjab", jac, sub, jac)
    return body, body_cov
