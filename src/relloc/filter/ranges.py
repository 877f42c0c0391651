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
from relloc.filter import compiled
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
_NO_ARMS = np.zeros((2, 0))
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
    symmetric Gaussian-plus-uniform model. The element-wise passes run in place (the same
    operations, in the same order, as the expressions in the comments), without a temporary
    per operation."""
    los = np.divide(residual, sigma)
    z = los.copy()
    los *= -0.5
    los *= z
    np.exp(los, out=los)  # exp(-0.5 * z * z)
    los *= (1.0 - nlos_fraction - eps) / (sigma * np.sqrt(2.0 * np.pi))
    if nlos_fraction <= 0.0:
        return los, los + eps / support
    w = np.sqrt(sigma * sigma + nlos_sigma * nlos_sigma)
    u = np.divide(residual, w, out=z)
    nlos = np.multiply(u, -0.5)
    nlos *= u
    np.exp(nlos, out=nlos)  # exp(-0.5 * u * u)
    # (2 / w) phi(u) Phi(alpha u), Phi by the logistic approximation
    nlos *= 2.0 * nlos_fraction / (w * np.sqrt(2.0 * np.pi))
    u *= -_LOGISTIC_PROBIT * (nlos_sigma / sigma)
    np.exp(u, out=u)
    u += 1.0
    nlos /= u  # nlos / (1 + exp(-_LOGISTIC_PROBIT * (nlos_sigma / sigma) * u))
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
    def fused(self) -> bool:
        """Whether :meth:`add_log_likelihood` can take this batch: no online bias, no state
        column (what every range of a team with calibrated or fixed biases is)."""
        return not self.conditions and not self.state_columns

    def add_log_likelihood(
        self, particles: FloatArray, layout: TeamLayout, out: FloatArray
    ) -> None:
        """Add :meth:`log_likelihood` of every particle row (``(M, D)``: the position columns
        of ``layout`` first) to ``out`` ``(M,)``, in compiled passes (:func:`fused_loglik`);
        only for a :attr:`fused` batch. Equal to the NumPy path to round-off (the sum of the
        ranges' logs taken as the log of their product)."""
        if not self.fused:
            raise ValueError("add_log_likelihood needs a batch without online biases")
        column = layout.columns_of_robots
        fused_loglik(
            particles,
            column[self.index_a],
            column[self.index_b],
            np.asarray(self.distance - self.bias, dtype=float),
            np.asarray(self.sigma, dtype=float),
            _NO_ARMS if self.arms is None else np.asarray(self.arms, dtype=float),
            float(self.outlier_fraction),
            float(self.max_range),
            float(self.nlos_fraction),
            float(self.nlos_sigma),
            out,
        )

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


_BLOCK = 1024
"""Particles per block of :func:`fused_loglik`: its coordinate planes and ``(K, block)``
exponents stay in the cache."""
_FLOAT_RANGE = 300.0
"""Decades a product of densities may span in :func:`fused_loglik` before it could under- or
overflow float64 (``1e-308 .. 1e308``, less a margin)."""
_LN2_HI, _LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e00
_C3, _C4, _C5, _C6, _C7, _C8, _C9, _C10, _C11, _C12 = (
    1.0 / math.factorial(n) for n in range(3, 13)
)
"""Taylor coefficients ``1 / n!`` of ``exp`` on ``|r| <= ln 2 / 2`` (relative error below
``1e-14``)."""


@compiled.njit(cache=True)
def _exp_inplace(x: FloatArray, bits: NDArray[np.int64]) -> None:
    """``x = exp(x)`` in place, to ``1e-14`` relative, zero below ``-708``: ``2^k exp(r)``, the
    power of two written as the bits of a float (``bits``: scratch of ``x``'s size); loops
    the compiler vectorises, unlike a call of ``math.exp`` per element."""
    n = x.shape[0]
    for i in range(n):
        v = min(max(x[i], -708.0), 709.0)
        k = math.floor(v * _INV_LN2 + 0.5)
        r = v - k * _LN2_HI - k * _LN2_LO
        p = r * _C12 + _C11  # Horner, written out: the compiler then vectorises the loop
        p = p * r + _C10
        p = p * r + _C9
        p = p * r + _C8
        p = p * r + _C7
        p = p * r + _C6
        p = p * r + _C5
        p = p * r + _C4
        p = p * r + _C3
        p = p * r + 0.5
        p = p * r + 1.0
        p = p * r + 1.0
        bits[i] = (np.int64(k) + 1023) << 52 if x[i] >= -708.0 else 0
        x[i] = p
    scale = bits.view(np.float64)
    for i in range(n):
        x[i] *= scale[i]


@compiled.njit(cache=True)
def fused_loglik(
    particles: FloatArray,
    ca: IntArray,
    cb: IntArray,
    target: FloatArray,
    sigma: FloatArray,
    arms: FloatArray,
    eps: float,
    support: float,
    nlos_fraction: float,
    nlos_sigma: float,
    out: FloatArray,
) -> None:
    """``out[i] +=`` the log-likelihood of particle row ``i`` under ranges ``target`` (measured
    less bias) between position columns ``ca``/``cb`` (-1: the reference at the origin), plus
    the tags' offsets ``arms`` ``(2, K)`` (``(2, 0)``: none): the symmetric model
    (``nlos_fraction`` 0) or the NLOS-aware mixture (:func:`range_mixture`), the Gaussian alone
    when both fractions are 0.

    Per block of particles: the rows as coordinate planes, then range by range the exponents
    of every particle, their ``exp`` (:func:`_exp_inplace`) and the product of the densities
    (contiguous loops the compiler vectorises). The sum of the ranges' logs is the log of their
    product: one ``log`` per particle for as many ranges as the uniform floor keeps the product
    inside float64 (every range without a floor, where a density can be zero)."""
    m, k_count = particles.shape[0], target.shape[0]
    nlos = nlos_fraction > 0.0
    floor = eps / support
    sqrt2pi = math.sqrt(2.0 * math.pi)
    inv_s, inv_w = np.empty(k_count), np.empty(k_count)
    a_los, a_nlos, log_norm = np.empty(k_count), np.empty(k_count), np.empty(k_count)
    top = 0.0
    for k in range(k_count):
        w = math.sqrt(sigma[k] * sigma[k] + nlos_sigma * nlos_sigma)
        inv_s[k], inv_w[k] = 1.0 / sigma[k], 1.0 / w
        a_los[k] = (1.0 - nlos_fraction - eps) / (sigma[k] * sqrt2pi)
        a_nlos[k] = 2.0 * nlos_fraction / (w * sqrt2pi) if nlos else 0.0
        log_norm[k] = math.log(sigma[k] * sqrt2pi)
        top = max(top, a_los[k] + a_nlos[k] + floor)
    gaussian = eps <= 0.0 and not nlos
    chunk = 1
    if floor > 0.0:
        decades = max(-math.log10(floor), math.log10(max(top, 1.0)), 1e-3)
        chunk = max(1, int(_FLOAT_RANGE / decades))
    dim = 0
    for k in range(k_count):
        dim = max(dim, ca[k] + 2, cb[k] + 2)
    size = min(m, _BLOCK)
    planes = np.zeros((dim + 2, size))  # the last two rows: the reference at the origin
    e0, e1, e2 = np.empty(size), np.empty(size), np.empty(size)
    bits = np.empty(size, dtype=np.int64)
    prod = np.empty(size)
    for start in range(0, m, _BLOCK):
        n = min(_BLOCK, m - start)
        for i in range(n):
            for c in range(dim):
                planes[c, i] = particles[start + i, c]
        for i in range(n):
            prod[i] = 1.0
        for k in range(k_count):
            ra = ca[k] if ca[k] >= 0 else dim
            rb = cb[k] if cb[k] >= 0 else dim
            pax, pay, pbx, pby = planes[ra], planes[ra + 1], planes[rb], planes[rb + 1]
            ax = arms[0, k] if arms.shape[1] else 0.0
            ay = arms[1, k] if arms.shape[1] else 0.0
            t, s, v = target[k], inv_s[k], inv_w[k]
            for i in range(n):
                dx = pax[i] - pbx[i] + ax
                dy = pay[i] - pby[i] + ay
                r = t - math.sqrt(dx * dx + dy * dy)
                e0[i] = -0.5 * (r * s) * (r * s)
                e1[i] = r * v
            if gaussian:
                for i in range(n):
                    out[start + i] += e0[i] - log_norm[k]
                continue
            _exp_inplace(e0[:n], bits[:n])
            a, f = a_los[k], floor
            if nlos:
                slope = -_LOGISTIC_PROBIT * nlos_sigma * s
                for i in range(n):
                    u = e1[i]
                    e2[i] = slope * u
                    e1[i] = -0.5 * u * u
                _exp_inplace(e1[:n], bits[:n])
                _exp_inplace(e2[:n], bits[:n])
                b = a_nlos[k]
                for i in range(n):
                    prod[i] *= a * e0[i] + b * e1[i] / (1.0 + e2[i]) + f
            else:
                for i in range(n):
                    prod[i] *= a * e0[i] + f
            if (k + 1) % chunk == 0 or k == k_count - 1:
                for i in range(n):
                    out[start + i] += math.log(prod[i])
                    prod[i] = 1.0


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
