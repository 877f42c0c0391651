"""The UWB range model: robust likelihoods of ranges between robots, and their linearisation.

With ``r = z - b - ||p_a - p_b||`` the residual of a range after the pair's bias ``b``, the
*symmetric* model is a Gaussian-plus-uniform mixture::

    p(r) = (1 - eps) N(r; 0, sigma^2) + eps / R

with ``eps`` the outlier fraction and ``R`` the support of the outliers. The uniform floor
bounds the damage one spike can do to a good particle.

The derivation: docs/explanation/internals.md, section ``relloc.filter.ranges``.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from relloc import geometry
from relloc.config import TeamConfig, UwbConfig
from relloc.events import RangeEvent, pair_key
from relloc.filter.measurement import (
    LinearRow,
    MeasurementModel,
    ModelContext,
    ValidationContext,
    finite,
)
from relloc.filter.state import TeamLayout

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
_LOGISTIC_PROBIT = 1.702
"""``Phi(x) ~ 1 / (1 + exp(-1.702 x))``: the logistic approximation of the normal CDF."""

# The mixture of both models; the Gaussian noise is the sensor's (``[uwb] sigma``, ``los_sigma``).
NLOS_FRACTION = 0.1
"""NLOS-aware model: weight of the non-line-of-sight part, fitted to the TIERS training table."""
NLOS_SIGMA = 0.3
"""NLOS-aware model: scale (m) of the half-normal excess delay of a blocked path."""
GROSS_FRACTION = 0.02
"""NLOS-aware model: weight of the uniform part (gross errors of any sign)."""
OUTLIER_FRACTION = 0.1
"""Symmetric model: weight of the uniform (NLOS/outlier) part."""
MAX_RANGE = 15.0
"""Support (m) of the uniform outlier density, and the longest range accepted (UWB's reach
indoors)."""


def _robust_gaussian_loglik(
    residual: FloatArray, sigma: FloatArray, eps: float, support: float
) -> FloatArray:
    """Elementwise log of ``(1-eps) N(residual; 0, sigma^2) + eps / support``.

    Computed in linear space (one ``exp`` and one ``log``, in place): exact, because the
    uniform floor keeps the sum away from zero, and about twice as fast as ``logaddexp``.
    """
    z = residual / sigma
    z *= z
    z *= -0.5
    if eps <= 0.0:
        z -= np.log(sigma) + _LOG_SQRT_2PI
        return z
    np.exp(z, out=z)
    z *= (1.0 - eps) / (sigma * np.sqrt(2.0 * np.pi))
    z += eps / support
    np.log(z, out=z)
    return z


def range_mixture(
    residual: FloatArray,
    sigma: FloatArray,
    eps: float,
    support: float,
    nlos_fraction: float,
    nlos_sigma: float,
) -> tuple[FloatArray, FloatArray]:
    """Line-of-sight density and total density of the range mixture (module docstring),
    elementwise; ``sigma`` broadcasts against ``residual``. ``nlos_fraction`` 0 is the
    symmetric Gaussian-plus-uniform model."""
    z = residual / sigma
    los = np.exp(-0.5 * z * z)
    los *= (1.0 - nlos_fraction - eps) / (sigma * np.sqrt(2.0 * np.pi))
    if nlos_fraction <= 0.0:
        return los, los + eps / support
    w = np.sqrt(sigma * sigma + nlos_sigma * nlos_sigma)
    u = residual / w
    nlos = np.exp(-0.5 * u * u)
    # (2 / w) phi(u) Phi(alpha u), Phi by the logistic approximation
    nlos *= 2.0 * nlos_fraction / (w * np.sqrt(2.0 * np.pi))
    nlos /= 1.0 + np.exp(-_LOGISTIC_PROBIT * (nlos_sigma / sigma) * u)
    total = los + nlos
    total += eps / support
    return los, total


def separable(uwb: UwbConfig, pair: str, in_state: bool) -> bool:
    """Whether an online bias can take the NLOS-aware model: its prior is a calibration (the
    line-of-sight peak it stands for is then pinned, and the one-sided excess cannot drag it:
    without, a bias and an excess are confounded, measured on one range: 0.108 m symmetric,
    0.165 NLOS-aware), and the particles carry it, not a Gaussian state column
    (``in_state``: that needs the linear, symmetric row)."""
    return pair in uwb.pairs and not in_state


def _model_sigma(group: Sequence[RangeEvent]) -> float:
    """The learned correction's own standard deviation for a pair's ranges of one batch (the
    median of their ``RangeEvent.sigma``), or 0 where no model gave one.

    It can only *widen* the range noise the config sets (the caller takes the larger): the
    model's sigma ranks ranges well but is not calibrated outside its training session
    (docs/explanation/range-correction.md), so a model that is unsure makes its ranges weigh less, while a confident
    one never makes them weigh more than an uncorrected range of the same pair would.
    """
    sigmas = [
        ev.sigma for ev in group if ev.sigma is not None and finite(ev.sigma) and ev.sigma > 0.0
    ]
    return float(statistics.median(sigmas)) if sigmas else 0.0


def pair_sigma(config: TeamConfig, node_pair: str, base: float) -> float:
    """Noise of a raw range of ``node_pair`` (after its scale is divided out): the pair's
    calibrated sigma, else ``base``, over its scale; an uncalibrated pair's ``base`` widened
    by ``uwb.default_bias_sigma`` (its bias is only the default)."""
    uwb = config.uwb
    cal = uwb.pairs.get(node_pair)
    if cal is None:
        return math.hypot(base, uwb.default_bias_sigma)
    return (cal.sigma if cal.sigma is not None else base) / cal.scale


@dataclass(frozen=True)
class RangeBatch(MeasurementModel):
    """``K`` ranges between robots ``index_a[k]`` and ``index_b[k]`` (indices into the team).

    ``distance`` is the measured range, ``bias`` the pair's fixed bias (``measured = true +
    bias``; a calibrated range scale is divided out by :meth:`build`) and ``sigma`` its noise.
    """

    events: ClassVar[tuple[type, ...]] = (RangeEvent,)
    stat: ClassVar[str] = "range"
    invariant: ClassVar[bool] = True
    needs_shared_heading: ClassVar[bool] = False
    ranged: ClassVar[bool] = True

    index_a: IntArray
    index_b: IntArray
    distance: FloatArray
    bias: FloatArray
    sigma: FloatArray
    outlier_fraction: float = OUTLIER_FRACTION
    max_range: float = MAX_RANGE
    bias_columns: IntArray | None = None
    """Sampled filter, online biases: per range, the state column of the particle's bias mean
    (the variance is the next column), or -1 where the bias is the fixed ``bias``; ``None``:
    all fixed."""
    nlos_fraction: float = 0.0
    """Weight of the non-line-of-sight (one-sided, too long) component; 0: the symmetric
    Gaussian-plus-uniform model. ``sigma`` is then the line-of-sight noise."""
    nlos_sigma: float = NLOS_SIGMA
    """Scale of the NLOS excess delay (half-normal, m)."""
    state_columns: tuple[tuple[int, ...], ...] = ()
    """Gaussian-sum filter, online biases: per range, the state columns whose sum the range
    sees on top of the fixed ``bias`` (the pair's bias and its time-correlated error); ``()``:
    none anywhere."""
    layout: TeamLayout | None = None
    """The state layout the ranges index (needed by :meth:`row` only)."""
    nodes: tuple[tuple[str, str], ...] = ()
    """Per range the tags (node ids) on robots ``index_a`` and ``index_b`` (a robot with
    several tags has a range per tag pair); ``()``: not known."""
    arms: FloatArray | None = None
    """Per range ``R(yaw_a) l_a - R(yaw_b) l_b`` ``(2, K)``: where the two tags sit off their
    robots' positions in the shared heading frame (lever arms turned by the odometry yaws at
    the batch), added to ``p_a - p_b``; ``None``: none, or the yaws are not known."""

    def __len__(self) -> int:
        return len(self.distance)

    # ---------------------------------------------------------------- building, validation
    @classmethod
    def build(cls, events: Sequence[RangeEvent], context: ModelContext) -> list[MeasurementModel]:
        """The range models of one batch: per robot pair its median range; raw ranges get the
        NLOS-aware model when ``context.range_model`` says so, an online bias included where
        :func:`separable`; ranges corrected upstream by a learned model get the symmetric one
        (the correction predicted the skewed part)."""
        config, layout = context.config, context.layout
        uwb = config.uwb
        groups: dict[tuple[int, int, str, str], list[RangeEvent]] = {}
        for m in events:  # per robot pair and tag pair (one tag per robot: per robot pair)
            ia, ib = layout.index(m.robot_a), layout.index(m.robot_b)
            na, nb = config.range_nodes(m)
            if ia > ib:
                ia, ib, na, nb = ib, ia, nb, na
            groups.setdefault((ia, ib, na, nb), []).append(m)
        if not groups:
            return []
        pairs, dist, bias, sigma, keys, model_sigma = [], [], [], [], [], []
        tags: list[tuple[str, str]] = []
        for (ia, ib, na, nb), group in groups.items():
            key = (ia, ib)
            nodes = config.range_nodes(group[0])
            node_pair = pair_key(*nodes)
            tags.append((na, nb))
            d = float(statistics.median(ev.distance for ev in group))  # a few values: no NumPy
            if all(ev.corrected for ev in group):
                b, s, node_pair = 0.0, uwb.sigma, ""
            elif node_pair in layout.bias_pairs:
                b, s = 0.0, uwb.sigma  # the bias is in the state
            else:
                b, scale, _ = uwb.calibration(*nodes)
                d, b, s = d / scale, b / scale, pair_sigma(config, node_pair, uwb.sigma)
            pairs.append(key)
            dist.append(d)
            bias.append(b)
            sigma.append(s)
            keys.append(node_pair)
            model_sigma.append(_model_sigma(group))
        idx = np.array(pairs, dtype=np.intp)
        dist_a, bias_a, sigma_a = np.array(dist), np.array(bias), np.array(sigma)
        arms = _arms(context, idx, tags)
        online = [k in layout.bias_pairs for k in keys]
        belief = np.array(
            [
                layout.bias_belief_column(k) if on else -1
                for k, on in zip(keys, online, strict=True)
            ],
            dtype=np.intp,
        )
        state = tuple(
            layout.bias_state_columns(k) if on else () for k, on in zip(keys, online, strict=True)
        )
        if context.range_model == "nlos":
            raw = np.array(
                [
                    bool(k) and (not on or separable(uwb, k, bool(st)))
                    for k, on, st in zip(keys, online, state, strict=True)
                ]
            )
        else:
            raw = np.zeros(len(keys), bool)
        out: list[MeasurementModel] = []
        for sel, nlos in ((raw, True), (~raw, False)):
            if not np.any(sel):
                continue
            if nlos:  # an online bias's uncertainty is in the state, not widened here
                s = np.array(
                    [
                        uwb.los_sigma if on else pair_sigma(config, k, uwb.los_sigma)
                        for k, on in zip(keys, online, strict=True)
                    ]
                )[sel]
                eps = GROSS_FRACTION if context.robust else 0.0
            else:
                s = sigma_a[sel]
                eps = OUTLIER_FRACTION if context.robust else 0.0
            s = np.maximum(s, np.array(model_sigma)[sel])  # an unsure correction weighs less
            rows = np.flatnonzero(sel)
            out.append(
                cls(
                    idx[sel, 0],
                    idx[sel, 1],
                    dist_a[sel],
                    bias_a[sel],
                    s,
                    eps,
                    MAX_RANGE,
                    belief[sel] if np.any(belief >= 0) else None,
                    nlos_fraction=NLOS_FRACTION if nlos and context.robust else 0.0,
                    nlos_sigma=NLOS_SIGMA,
                    state_columns=tuple(state[i] for i in rows) if any(state) else (),
                    layout=layout,
                    nodes=tuple(tags[i] for i in rows),
                    arms=None if arms is None else arms[:, sel],
                )
            )
        return out

    @classmethod
    def stream(cls, event: RangeEvent) -> tuple[str, ...]:
        """One stream per robot pair, whichever robot's node reported it."""
        return ("range", *sorted((event.robot_a, event.robot_b)))

    @classmethod
    def heard(cls, event: RangeEvent) -> tuple[str, ...]:
        return (event.robot_a, event.robot_b)

    @classmethod
    def rejection(cls, event: RangeEvent, context: ValidationContext) -> str | None:
        """Unknown robots, a robot ranging itself, a non-finite, non-positive or out-of-range
        distance, a measurement the filter has moved past, a node pair the online-bias state
        has no column for, and a range equal to its pair's previous one."""
        names = context.layout.robots
        if event.robot_a not in names or event.robot_b not in names:
            return "unknown_robot"
        if event.robot_a == event.robot_b:
            return "self_range"
        d = event.distance
        if not finite(d) or d <= 0.0 or d > MAX_RANGE:
            return "invalid_range"
        if context.is_late(event.t):
            return "late_measurement"
        bias_pairs = context.layout.bias_pairs
        if (
            bias_pairs
            and not event.corrected
            and pair_key(*context.config.range_nodes(event)) not in bias_pairs
        ):
            return "unknown_node_pair"  # online biases: the state has a column per configured pair only
        last = context.memory(cls)
        key = (
            (event.robot_a, event.robot_b)
            if event.robot_a < event.robot_b
            else (event.robot_b, event.robot_a)
        )
        if last.get(key) == d:
            # Equal to the pair's previous range: a driver re-publishing a stale sample, or a
            # new one that the 1 cm resolution made equal. Dropped either way: the likelihood
            # treats each batch as independent evidence, and a repeated value is not.
            return "repeated_range"
        last[key] = d
        return None

    # ---------------------------------------------------------------- sampled filter
    def predicted(self, positions: FloatArray) -> FloatArray:
        """True distances of each particle's pairs (between their tags), shape ``(K, M)``."""
        d = np.take(positions, self.index_a, axis=1) - np.take(positions, self.index_b, axis=1)
        if self.arms is not None:
            d += self.arms[:, :, None]
        return geometry.norm(d, axis=0, overwrite=True)

    def _residual_and_sigma(
        self, positions: FloatArray, particles: FloatArray | None
    ) -> tuple[FloatArray, FloatArray]:
        d = self.predicted(positions)
        residual = (self.distance - self.bias)[:, None] - d
        sigma = self.sigma[:, None]  # (K, 1): broadcasts against (K, M)
        if particles is None:
            return residual, sigma
        if self.bias_columns is not None:
            online = self.bias_columns >= 0
            if np.any(online):
                cols = self.bias_columns[online]
                residual[online] -= particles[:, cols].T
                sigma = np.repeat(sigma, residual.shape[1], axis=1)
                sigma[online] = np.sqrt(self.sigma[online, None] ** 2 + particles[:, cols + 1].T)
        for k, columns in enumerate(self.state_columns):
            for c in columns:
                residual[k] -= particles[:, c]
        return residual, sigma

    def log_likelihood(
        self, positions: FloatArray, particles: FloatArray | None = None
    ) -> FloatArray:
        residual, sigma = self._residual_and_sigma(positions, particles)
        if self.nlos_fraction > 0.0:
            _, total = range_mixture(
                residual,
                sigma,
                self.outlier_fraction,
                self.max_range,
                self.nlos_fraction,
                self.nlos_sigma,
            )
            return np.log(total).sum(axis=0)
        ll = _robust_gaussian_loglik(residual, sigma, self.outlier_fraction, self.max_range)
        return ll.sum(axis=0)

    @property
    def conditions(self) -> bool:
        return self.bias_columns is not None and bool(np.any(self.bias_columns >= 0))

    def condition(self, positions: FloatArray, particles: FloatArray) -> None:
        """Update each particle's online bias beliefs with this batch, in place.

        The Kalman gain is scaled by the probability that the range is an inlier under the
        robust mixture, so an NLOS spike barely moves the bias.
        """
        if not self.conditions:
            return
        assert self.bias_columns is not None
        online = self.bias_columns >= 0
        residual, sigma = self._residual_and_sigma(positions, particles)
        r, s = residual[online], sigma[online]
        cols = self.bias_columns[online]
        var = particles[:, cols + 1].T  # (K', M)
        los, total = range_mixture(
            r, s, self.outlier_fraction, self.max_range, self.nlos_fraction, self.nlos_sigma
        )
        inlier = los / total
        gain = inlier * var / (s * s)
        particles[:, cols] += (gain * r).T
        particles[:, cols + 1] = ((1.0 - gain) * var).T

    # ---------------------------------------------------------------- Gaussian-sum filter
    @property
    def rows(self) -> int:
        return len(self.distance)

    def row(self, k: int, mean: FloatArray) -> LinearRow:
        """Range ``k`` linearised at every Gaussian's mean: ``d(|p_a - p_b|)/dp = +-e`` (the
        unit vector from b to a) and 1 for every online bias column it sees."""
        if self.nlos_fraction > 0.0 or self.bias_columns is not None:
            raise ValueError(
                "only the symmetric range model with state-column biases has a linear row"
            )
        if self.layout is None:
            raise ValueError("a range model needs its layout to be linearised")
        n = mean.shape[0]
        sa = self.layout.slot_of(int(self.index_a[k]))
        sb = self.layout.slot_of(int(self.index_b[k]))
        pa = mean[:, 2 * sa : 2 * sa + 2] if sa >= 0 else np.zeros((n, 2))
        pb = mean[:, 2 * sb : 2 * sb + 2] if sb >= 0 else np.zeros((n, 2))
        diff = pa - pb if self.arms is None else pa - pb + self.arms[:, k]
        dist, e = geometry.direction(diff)
        cols: list[int] = []
        coefs: list[FloatArray] = []
        if sa >= 0:
            cols += [2 * sa, 2 * sa + 1]
            coefs += [e[:, 0], e[:, 1]]
        if sb >= 0:
            cols += [2 * sb, 2 * sb + 1]
            coefs += [-e[:, 0], -e[:, 1]]
        predicted = dist + float(self.bias[k])
        for c in self.state_columns[k] if self.state_columns else ():
            cols.append(c)
            coefs.append(np.ones(n))
            predicted = predicted + mean[:, c]
        return LinearRow(
            np.array(cols),
            np.stack(coefs, axis=1),
            float(self.distance[k]) - predicted,
            float(self.sigma[k]) ** 2,
            self.outlier_fraction,
            self.max_range,
        )


def _arms(context: ModelContext, pairs: IntArray, tags: list[tuple[str, str]]) -> FloatArray | None:
    """Per range (team index pair, its tags) where the tags sit off the robots' positions in
    the shared heading frame (:attr:`RangeBatch.arms`), from the odometry yaws of the batch;
    ``None`` where no tag has a lever arm, the filter has no shared heading frame, or a robot
    with an arm has no yaw (its tags are then taken at its position)."""
    config = context.config
    yaws = context.yaws
    if not config.has_lever_arms or not context.shared_heading or yaws is None:
        return None
    robots = context.layout.robots
    out = np.zeros((2, len(tags)))
    for k, ((ia, ib), (na, nb)) in enumerate(zip(pairs.tolist(), tags, strict=True)):
        for robot, node, sign in ((robots[ia], na, 1.0), (robots[ib], nb, -1.0)):
            arm = config.lever_arm(node)
            if arm[0] == 0.0 and arm[1] == 0.0:
                continue
            yaw = yaws.get(robot)
            if yaw is None or not math.isfinite(yaw):
                return None
            c, s = math.cos(yaw), math.sin(yaw)
            out[0, k] += sign * (c * arm[0] - s * arm[1])
            out[1, k] += sign * (s * arm[0] + c * arm[1])
    return out
