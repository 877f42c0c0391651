"""An honest summary of a posterior over formations: its dominant mode, what is observable, and
the shape that is known even when the orientation is not.

Both filters hold ``M`` weighted hypotheses about the team's relative positions (particles, or
the means of Gaussians with their covariances). The weighted mean of all of them is a poor
estimate whenever the posterior has several modes: ranges alone cannot tell a formation from
its rotations about the reference robot or its mirror image, so a team at rest has a posterior
spread over a ring (two rings, one per handedness), and before motion has resolved them the
mirror images are separate modes. The mean of separated modes is a place where no mode is.

The derivation: docs/explanation/internals.md, section ``relloc.filter.summary``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from relloc.estimate import covariance_of
from relloc.events import pair_key
from relloc.filter.gauge import gauge, procrustes_fit
from relloc.filter.measurement import MeasurementModel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

MODE_BINS = 36
"""Bins of the orientation circle (10 degrees each) per handedness."""
MODE_MIN_BIN_WEIGHT = 0.005
"""A bin belongs to a mode when it holds more than this fraction of the weight: above the
share of the hypotheses re-drawn from the prior (1 % over 72 bins), below any real mode."""
MODE_MIN_WEIGHT = 0.01
"""Modes lighter than this are not counted in ``n_modes``."""
ORIENTATION_MAX_STD = 0.3
"""Circular std (rad) of the dominant mode's orientation under which it counts as resolved."""
MOTION_TO_RESOLVE = 0.3
"""Net displacement (m) of some robot from where it started after which motion may have told
the orientation (the particles then decide)."""
AT_REST_PATH = 0.001
"""Path length (m) of odometry under which a robot counts as never having moved: parked wheel
odometry reports no motion at all (exactly zero on the parked TIERS robots), so this is only a
margin for rounding; the first real motion exceeds it."""


class Evidence:
    """What a filter has fused that can break the rotation/reflection symmetry: measurement
    models that are not invariant to it, and each robot's odometry (net displacement and path
    length)."""

    def __init__(self, n_robots: int) -> None:
        self.non_invariant = 0
        self.offset = np.zeros((n_robots, 2))
        self.max_offset = 0.0
        self.path = np.zeros(n_robots)

    def moved(self, disp: FloatArray) -> None:
        """Add one step's displacements ``(N, 2)``."""
        d = np.nan_to_num(disp)
        self.offset += d
        self.path += np.hypot(d[:, 0], d[:, 1])
        self.max_offset = max(
            self.max_offset, float(np.max(np.hypot(self.offset[:, 0], self.offset[:, 1])))
        )

    def fused(self, models: Sequence[MeasurementModel]) -> None:
        self.non_invariant += sum(1 for m in models if not getattr(m, "invariant", True))

    def reset(self) -> None:
        """Forget the motion (the filter restarted from the symmetric start)."""
        self.offset[:] = 0.0
        self.path[:] = 0.0
        self.max_offset = 0.0
        self.non_invariant = 0

    @property
    def can_resolve(self) -> bool:
        return self.non_invariant > 0 or self.max_offset >= MOTION_TO_RESOLVE

    @property
    def symmetric(self) -> bool:
        """Whether the exact posterior is still invariant under the rotations and mirror images
        about the reference: only invariant models fused and no robot ever moved. A filter
        may then re-spread its hypotheses over the symmetries at no cost in information."""
        return self.non_invariant == 0 and float(self.path.max(initial=0.0)) < AT_REST_PATH


@dataclass(frozen=True)
class ModeSummary:
    """The honest summary of a posterior over formations (see the module docstring)."""

    mean: FloatArray  # (K, 2) published positions
    cov: FloatArray  # (K, 2, 2) published covariances
    weighted_mean: FloatArray  # (K, 2) mean over every hypothesis (diagnostic)
    mode_weight: float
    n_modes: int
    orientation_std: float  # circular std (rad) of the dominant mode's orientation
    orientation_observable: bool
    shape: FloatArray  # (K, 2) in the declared gauge
    shape_cov: FloatArray  # (K, 2, 2)
    distances: FloatArray  # (K+1, K+1, 2): mean and std of each pair's distance, reference first
    members: NDArray[np.bool_] = field(repr=False)  # (M,) hypotheses of the dominant mode


def estimate_fields(
    summary: ModeSummary, reference: str, others: Sequence[str], *, shape: bool = True
) -> dict[str, Any]:
    """The :class:`~relloc.estimate.Estimate` fields of ``summary`` (robots ``others`` in state
    order; pairs keyed by :func:`~relloc.events.pair_key`). ``shape`` False: no consumer reads
    the shape and the distances (a live server whose shape key nobody subscribes to), which
    are then left out (empty) and, where deferred, uncomputed."""
    wm = summary.weighted_mean.tolist()
    out = {
        "orientation_observable": summary.orientation_observable,
        "mode_weight": summary.mode_weight,
        "n_modes": summary.n_modes,
        "weighted_mean": {r: (wm[k][0], wm[k][1]) for k, r in enumerate(others)},
    }
    if not shape:
        return out
    names = (reference, *others)
    d = summary.distances.tolist()
    g = summary.shape.tolist()
    out["shape"] = {r: (g[k][0], g[k][1]) for k, r in enumerate(others)}
    out["shape_covariances"] = {
        r: covariance_of(summary.shape_cov[k]) for k, r in enumerate(others)
    }
    out["shape_gauge"] = others[0]
    out["distances"] = {
        pair_key(a, b): (d[i][j][0], d[i][j][1])
        for i, a in enumerate(names)
        for j, b in enumerate(names)
        if j > i
    }
    return out


_BEFORE = (np.arange(MODE_BINS) - 1) % MODE_BINS
_AFTER = (np.arange(MODE_BINS) + 1) % MODE_BINS


def _modes(angle: FloatArray, hand: FloatArray, w: FloatArray) -> tuple[IntArray, list[float]]:
    """Mode label of every hypothesis (-1: in no mode), labels ordered by decreasing weight,
    and each mode's weight (the weights of its bins)."""
    a = angle + np.pi  # in place from here: (angle + pi) / 2 pi * MODE_BINS, floored
    a /= 2.0 * np.pi
    a *= MODE_BINS
    cell = np.floor(a, out=a).astype(np.intp)
    cell %= MODE_BINS
    cell[hand < 0] += MODE_BINS
    hist = np.bincount(cell, weights=w, minlength=2 * MODE_BINS)
    label_of_cell = np.full(2 * MODE_BINS, -1, dtype=np.intp)
    runs: list[list[int]] = []
    heavy = (hist > MODE_MIN_BIN_WEIGHT).reshape(2, MODE_BINS)
    # a mode's tails: its neighbour bins (on the circle)
    occupied = (heavy | heavy[:, _BEFORE] | heavy[:, _AFTER]).tolist()
    for h in range(2):
        occ = occupied[h]
        if not any(occ):
            continue
        if all(occ):
            runs.append([h * MODE_BINS + i for i in range(MODE_BINS)])
            continue
        start = occ.index(False)  # walk the circle from an empty bin
        current: list[int] = []
        for j in range(1, MODE_BINS + 1):
            i = (start + j) % MODE_BINS
            if occ[i]:
                current.append(h * MODE_BINS + i)
            elif current:
                runs.append(current)
                current = []
        if current:
            runs.append(current)
    mass = hist.tolist()
    weighed = sorted(((sum(mass[i] for i in run), run) for run in runs), key=lambda wr: -wr[0])
    for k, (_, run) in enumerate(weighed):
        label_of_cell[run] = k
    return label_of_cell[cell], [wr[0] for wr in weighed]


SUMMARY_SAMPLE = 1024
"""Hypotheses (an even stride through the cloud) from which the template formation, the shape
and the distances are computed: the template only needs to be roughly right (the angles of
every hypothesis are exact fits to it), the shape and distances are means whose Monte Carlo
error over 1024 hypotheses is about 3 % of the posterior's spread."""


@functools.cache
def _pairs(n: int) -> tuple[IntArray, IntArray]:
    """``np.triu_indices(n, 1)``, made once per team size (read-only)."""
    i, j = np.triu_indices(n, 1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


def _normalised(w: FloatArray) -> FloatArray:
    total = float(w.sum())
    return w / total if total > 0 else np.full(w.shape, 1.0 / w.size)


def _wsum(a: FloatArray, w: FloatArray) -> FloatArray:
    """``a @ w`` for planes ``(K, M)``, by einsum: BLAS's matrix-vector product of a single row
    (one robot) stalls for tens of milliseconds on a busy machine."""
    return np.einsum("km,m->k", a, w)


def _planes(m: int, k: int) -> FloatArray:
    """An empty ``(5K, M)`` block of coordinate planes: ``x``, ``y``, then (:func:`_products`)
    ``x * x``, ``y * y``, ``x * y``, so that the weighted sums of all are one einsum."""
    return np.empty((5 * k, m))


def _products(planes: FloatArray) -> FloatArray:
    k = planes.shape[0] // 5
    x, y = planes[:k], planes[k : 2 * k]
    np.multiply(x, x, out=planes[2 * k : 3 * k])
    np.multiply(y, y, out=planes[3 * k : 4 * k])
    np.multiply(x, y, out=planes[4 * k :])
    return planes


def _moments(
    sums: FloatArray, w: FloatArray, covs: FloatArray | None
) -> tuple[FloatArray, FloatArray]:
    """Weighted mean ``(K, 2)`` and per-robot covariance ``(K, 2, 2)`` from the weighted sums
    ``(5K,)`` of the planes ``x``, ``y``, ``x * x``, ``y * y``, ``x * y`` (:func:`_planes`)
    under normalised weights ``w`` (plus the weighted member covariances ``covs``
    ``(M, K, 2, 2)``, if any). Second moments minus the squared mean: no centred copy;
    positions are metres, far above float64 cancellation."""
    k = sums.shape[0] // 5
    mx, my, sxx, syy, sxy = (
        sums[:k],
        sums[k : 2 * k],
        sums[2 * k : 3 * k],
        sums[3 * k : 4 * k],
        sums[4 * k :],
    )
    mean = np.empty((k, 2))
    mean[:, 0], mean[:, 1] = mx, my
    cov = np.empty((k, 2, 2))
    cov[:, 0, 0] = np.maximum(sxx - mx * mx, 0.0)
    cov[:, 1, 1] = np.maximum(syy - my * my, 0.0)
    cov[:, 0, 1] = cov[:, 1, 0] = sxy - mx * my
    if covs is not None:
        cov += np.einsum("m,mkab->kab", w, covs)
    return mean, cov


def _onto(
    x: FloatArray, y: FloatArray, c: FloatArray, s: FloatArray, hand: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Formations (planes ``(K, M)``) turned back by their angle (``c``, ``s``) and un-mirrored:
    onto the template."""
    return c * x + s * y, hand * (c * y - s * x)


def summarize(
    rel: FloatArray,
    w: FloatArray,
    covs: FloatArray | None = None,
    *,
    can_resolve: bool = True,
    floor: float = 0.0,
    deferred: bool = False,
) -> ModeSummary:
    """The honest summary of hypotheses ``rel`` ``(M, K, 2)`` (relative positions of the
    non-reference robots) with normalised weights ``w`` ``(M,)`` and, for Gaussians, their
    per-robot position covariances ``covs`` ``(M, K, 2, 2)``. ``can_resolve``: whether what was
    fused could have broken the rotation/reflection symmetry (:class:`Evidence`). ``floor``
    (m^2) is added to every published and shape variance: the share of the error that the
    hypotheses' spread cannot show (:attr:`relloc.estimators.particle.filter.ParticleFilter.covariance_floor`).
    ``deferred``: return a :class:`DeferredSummary`, its shape and distances computed on first
    read."""
    rel = np.asarray(rel, float)
    w = np.asarray(w, float)
    w = _normalised(w)
    m, k, _ = rel.shape
    planes = _planes(m, k)
    planes[:k], planes[k : 2 * k] = rel[:, :, 0].T, rel[:, :, 1].T
    weighted_mean, all_cov = _moments(_wsum(_products(planes), w), w, covs)

    # A first template: the weighted mean gauge form of an even stride through the cloud (the
    # whole cloud below 2 SUMMARY_SAMPLE hypotheses: no copy of it then).
    step = max(1, m // SUMMARY_SAMPLE)
    sub = np.arange(0, m, step)
    ws = _normalised(w if step == 1 else w[sub])
    template = np.einsum("m,mkd->kd", ws, gauge(rel if step == 1 else rel[sub]))
    c, s, hand = procrustes_fit(planes, template)
    labels, mode_w = _modes(np.arctan2(s, c), hand, w)
    members = labels == 0 if mode_w else np.ones(m, dtype=bool)
    n_modes = max(1, sum(1 for mw in mode_w if mw >= MODE_MIN_WEIGHT))
    mode_weight = float(np.sum(w, where=members))
    everything = bool(members.all())
    wm = w if everything else w * members / max(mode_weight, 1e-300)

    # The dominant mode's circular spread of orientation (about the template: an offset
    # does not change it).
    rbar = min(
        math.hypot(float(np.einsum("m,m->", wm, c)), float(np.einsum("m,m->", wm, s))), 1.0
    )  # round-off
    orientation_std = (
        math.pi
        if rbar <= math.exp(-0.5 * math.pi**2)
        else min(math.sqrt(-2.0 * math.log(rbar)), math.pi)
    )

    if can_resolve:
        mean, cov = (
            (weighted_mean, all_cov) if everything else _moments(_wsum(planes, wm), wm, covs)
        )
    else:
        # The exact posterior is invariant under rotations about the reference: its moments.
        r2 = np.diagonal(all_cov, axis1=1, axis2=2).sum(axis=1) + np.sum(weighted_mean**2, axis=1)
        mean = np.zeros((k, 2))
        cov = 0.5 * r2[:, None, None] * np.eye(2)[None]
    cov = cov + floor * np.eye(2)[None]

    fields = (
        mean,
        cov,
        weighted_mean,
        mode_weight,
        n_modes,
        orientation_std,
        bool(can_resolve and orientation_std < ORIENTATION_MAX_STD),
    )
    tail = _Tail(
        planes[:k],
        planes[k : 2 * k],
        (c, s, hand) if step == 1 else (c[sub], s[sub], hand[sub]),
        sub,
        ws,
        covs,
        floor,
    )
    if deferred:
        return DeferredSummary.of(fields, members, tail)
    shape, shape_cov = tail.shape()
    return ModeSummary(*fields, shape, shape_cov, tail.distances(), members)


class _Tail:
    """What the shape and the pairwise distances are computed from: the even stride through
    the cloud and its fit to the template (:func:`summarize`)."""

    def __init__(
        self,
        x: FloatArray,
        y: FloatArray,
        fit: tuple[FloatArray, FloatArray, FloatArray],
        sub: IntArray,
        ws: FloatArray,
        covs: FloatArray | None,
        floor: float,
    ) -> None:
        # x[:, sub] is laid out hypothesis-major (a gather along the last axis): the sums over
        # it below depend on that layout to the last bit, so it stays a gather even for step 1.
        self.xs, self.ys = x[:, sub], y[:, sub]
        self.fit, self.sub, self.ws, self.covs, self.floor = fit, sub, ws, covs, floor

    def shape(self) -> tuple[FloatArray, FloatArray]:
        """The mean formation in the declared gauge ``(K, 2)`` and its covariance ``(K, 2, 2)``."""
        ws, covs, floor = self.ws, self.covs, self.floor
        k = self.xs.shape[0]
        ax, ay = _onto(self.xs, self.ys, *self.fit)
        sums = np.concatenate([_wsum(a, ws) for a in (ax, ay, ax * ax, ay * ay, ax * ay)])
        shape_mean, shape_cov = _moments(sums, ws, None)
        if covs is not None:  # a member's own covariance turns with it; its trace is what survives
            shape_cov += (
                0.5
                * np.einsum("m,mk->k", ws, np.trace(covs[self.sub], axis1=2, axis2=3))[
                    :, None, None
                ]
                * np.eye(2)
            )
        g = gauge(shape_mean[None])[0]
        a0 = math.atan2(shape_mean[0, 1], shape_mean[0, 0])  # the same map for the covariance
        rot = np.array([[math.cos(a0), math.sin(a0)], [-math.sin(a0), math.cos(a0)]])
        if k > 1 and (rot @ shape_mean[1])[1] < 0.0:
            rot = np.diag([1.0, -1.0]) @ rot
        return g, np.einsum("ab,kbc,dc->kad", rot, shape_cov, rot) + floor * np.eye(2)[None]

    def distances(self) -> FloatArray:
        """Mean and std of every pair's distance ``(K+1, K+1, 2)``, the reference (index 0)
        included."""
        xs, ys, ws = self.xs, self.ys, self.ws
        k = xs.shape[0]
        i, j = _pairs(k + 1)
        px = np.zeros((k + 1, xs.shape[1]))
        py = np.zeros((k + 1, xs.shape[1]))
        px[1:], py[1:] = xs, ys
        dx, dy = px[i] - px[j], py[i] - py[j]
        dd = dx * dx + dy * dy
        dm = _wsum(np.sqrt(dd), ws)
        ds = np.sqrt(np.maximum(_wsum(dd, ws) - dm * dm, 0.0))
        distances = np.zeros((k + 1, k + 1, 2))
        distances[i, j, 0] = distances[j, i, 0] = dm
        distances[i, j, 1] = distances[j, i, 1] = ds
        return distances


class _OnRead:
    """A field of :class:`DeferredSummary`: the value given, else computed on first read."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name
        self.slot = "_" + name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        value = obj.__dict__.get(self.slot)
        if value is None:
            obj._materialize(self.name)
            value = obj.__dict__[self.slot]
        return value

    def __set__(self, obj: Any, value: Any) -> None:
        obj.__dict__[self.slot] = value


class DeferredSummary(ModeSummary):
    """A :class:`ModeSummary` whose shape (with its covariance) and pairwise distances are
    computed on first read, to the same bits as :func:`summarize` computes them at once: the
    moments, modes and observability a filter needs every step are there from the start, the
    rest only where some consumer reads it (a published estimate, the watchdog's distances)."""

    shape = _OnRead()
    shape_cov = _OnRead()
    distances = _OnRead()

    @classmethod
    def of(
        cls, fields: tuple[Any, ...], members: NDArray[np.bool_], tail: _Tail
    ) -> DeferredSummary:
        out = cls(*fields, None, None, None, members)  # type: ignore[call-arg]
        out.__dict__["_tail"] = tail
        return out

    def _materialize(self, name: str) -> None:
        tail: _Tail = self.__dict__["_tail"]
        if name == "distances":
            self.__dict__["_distances"] = tail.distances()
        else:
            self.__dict__["_shape"], self.__dict__["_shape_cov"] = tail.shape()

    @property
    def computed(self) -> frozenset[str]:
        """Which deferred parts have been computed so far (``shape``, ``distances``)."""
        d = self.__dict__
        return frozenset(
            n
            for n, slot in (("shape", "_shape"), ("distances", "_distances"))
            if d.get(slot) is not None
        )
