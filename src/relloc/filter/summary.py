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
from relloc.filter import compiled
from relloc.filter.gauge import gauge, gauge_planes, procrustes_fit
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
        d = disp if np.isfinite(disp).all() else np.nan_to_num(disp)
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
    x, y = planes[:k], planes[k : 2 * k]
    template = np.einsum(
        "m,mkd->kd", ws, gauge_planes(x, y) if step == 1 else gauge_planes(x[:, sub], y[:, sub])
    )
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


# ----------------------------------------------------------------------------- compiled particles
def summarize_particles(
    particles: FloatArray,
    k: int,
    w: FloatArray,
    *,
    can_resolve: bool = True,
    floor: float = 0.0,
    deferred: bool = False,
) -> ModeSummary:
    """:func:`summarize` of the particle rows ``particles`` ``(M, D)`` (robot ``j``'s relative
    position in columns ``2j, 2j + 1``, ``j < k``; further columns ignored) with weights ``w``.

    Compiled (:func:`_summary_core`), one pass over the rows instead of dozens of NumPy calls
    over coordinate planes: each particle's weighted moments are summed, and it is fitted to
    the template (made first from the same even stride through the cloud) and binned by
    orientation. The same quantities to round-off (sums in another order; the bin found by
    comparing the cosine of the fit with the bins' edges, not through ``atan2``), the same
    stride for the shape and distances. Only a posterior with more than one mode takes a
    second pass, for its dominant mode's moments (accumulating them per bin in the first pass
    costs more than that pass)."""
    (
        mean,
        cov,
        weighted_mean,
        mode_weight,
        n_modes,
        orientation_std,
        members,
        sample,
        ws,
        template,
    ) = _summary_core(particles, k, np.asarray(w, dtype=float), can_resolve, floor, _COS_EDGES)
    fields = (
        mean,
        cov,
        weighted_mean,
        mode_weight,
        n_modes,
        orientation_std,
        bool(can_resolve and orientation_std < ORIENTATION_MAX_STD),
    )
    tail = _SampleTail(sample, k, ws, template, floor)
    if deferred:
        return DeferredSummary.of(fields, members, tail)
    shape, shape_cov = tail.shape()
    return ModeSummary(*fields, shape, shape_cov, tail.distances(), members)


_COS_EDGES = np.cos(np.arange(1, MODE_BINS // 2) * (2.0 * np.pi / MODE_BINS))
"""Cosines of the orientation bins' inner edges on a half circle (:func:`_orientation_bin`)."""


@compiled.njit(cache=True)
def _summary_core(
    particles: FloatArray,
    k: int,
    w: FloatArray,
    can_resolve: bool,
    floor: float,
    cos_edges: FloatArray,
) -> tuple[
    FloatArray,
    FloatArray,
    FloatArray,
    float,
    int,
    float,
    NDArray[np.bool_],
    FloatArray,
    FloatArray,
    FloatArray,
]:
    """:func:`summarize_particles` but the summary's assembly: the published mean and
    covariance, the weighted mean, the mode's weight, the count of modes, the orientation's
    circular std, the members, and the stride sample with its weights and template."""
    m = particles.shape[0]
    total = 0.0
    for i in range(m):
        total += w[i]
    wn = np.empty(m)
    for i in range(m):
        wn[i] = w[i] / total if total > 0.0 else 1.0 / m
    step = max(1, m // SUMMARY_SAMPLE)
    n_sample = (m + step - 1) // step
    sample = np.empty((n_sample, 2 * k))
    ws = np.empty(n_sample)
    sample_total = 0.0
    for i in range(n_sample):
        sample[i] = particles[i * step, : 2 * k]
        ws[i] = wn[i * step]
        sample_total += ws[i]
    for i in range(n_sample):
        ws[i] = ws[i] / sample_total if sample_total > 0.0 else 1.0 / n_sample
    template = _template(sample, k, ws)
    cell, bins, sums = _fit_and_bin(particles, k, wn, 1.0, template, cos_edges)
    label_of_cell, mode_w = _mode_labels(bins[:, 0].copy())
    weighted_mean, all_cov = _moments_of(sums, k)
    any_mode = mode_w.shape[0] > 0
    members = np.empty(m, dtype=np.bool_)
    everything = True
    for i in range(m):
        members[i] = label_of_cell[cell[i]] == 0 if any_mode else True
        everything = everything and members[i]
    dominant = np.zeros(3)  # weight, weight * cos, weight * sin of the fit
    for b in range(bins.shape[0]):
        if label_of_cell[b] == 0 or not any_mode:
            dominant += bins[b]
    n_modes = 0
    for mw in mode_w:
        n_modes += mw >= MODE_MIN_WEIGHT
    n_modes = max(1, n_modes)
    mode_weight = dominant[0]
    scale = 1.0 / max(mode_weight, 1e-300)
    rbar = min(math.hypot(dominant[1] * scale, dominant[2] * scale), 1.0)
    orientation_std = math.pi
    if rbar > math.exp(-0.5 * math.pi**2):
        orientation_std = min(math.sqrt(-2.0 * math.log(rbar)), math.pi)
    if can_resolve and everything:
        mean, cov = weighted_mean.copy(), all_cov.copy()
    elif can_resolve:
        mean, cov = _moments_of(_member_sums(particles, k, wn, scale, members), k)
    else:  # the exact posterior is invariant under rotations about the reference: its moments
        mean = np.zeros((k, 2))
        cov = np.zeros((k, 2, 2))
        for j in range(k):
            r2 = all_cov[j, 0, 0] + all_cov[j, 1, 1]
            r2 += weighted_mean[j, 0] ** 2 + weighted_mean[j, 1] ** 2
            cov[j, 0, 0] = cov[j, 1, 1] = 0.5 * r2
    for j in range(k):
        cov[j, 0, 0] += floor
        cov[j, 1, 1] += floor
    return (
        mean,
        cov,
        weighted_mean,
        mode_weight,
        n_modes,
        orientation_std,
        members,
        sample,
        ws,
        template,
    )


@compiled.njit(cache=True)
def _moments_of(sums: FloatArray, k: int) -> tuple[FloatArray, FloatArray]:
    """:func:`_moments` without member covariances, compiled."""
    mean = np.empty((k, 2))
    cov = np.empty((k, 2, 2))
    for j in range(k):
        mx, my = sums[j], sums[k + j]
        mean[j, 0], mean[j, 1] = mx, my
        cov[j, 0, 0] = max(sums[2 * k + j] - mx * mx, 0.0)
        cov[j, 1, 1] = max(sums[3 * k + j] - my * my, 0.0)
        cov[j, 0, 1] = cov[j, 1, 0] = sums[4 * k + j] - mx * my
    return mean, cov


@compiled.njit(cache=True)
def _shape_of(
    sample: FloatArray, k: int, ws: FloatArray, template: FloatArray, floor: float
) -> tuple[FloatArray, FloatArray]:
    """:meth:`_Tail.shape` of the sample, compiled: the moments of the formations turned onto
    the template, the mean put in the gauge (:func:`relloc.filter.gauge.gauge`) and the
    covariance turned with it."""
    mean, cov = _moments_of(_shape_sums(sample, k, ws, template), k)
    a0 = math.atan2(mean[0, 1], mean[0, 0])
    c, s = math.cos(a0), math.sin(a0)
    flip = 1.0
    if k > 1 and c * mean[1, 1] - s * mean[1, 0] < 0.0:
        flip = -1.0
    g = np.empty((k, 2))
    out = np.empty((k, 2, 2))
    for j in range(k):
        x, y = mean[j, 0], mean[j, 1]
        g[j, 0] = c * x + s * y
        g[j, 1] = flip * (c * y - s * x)
        # rot = [[c, s], [-flip s, flip c]]; out = rot cov rot^T + floor
        r00, r01, r10, r11 = c, s, -flip * s, flip * c
        a, b, d = cov[j, 0, 0], cov[j, 0, 1], cov[j, 1, 1]
        t00, t01 = r00 * a + r01 * b, r00 * b + r01 * d
        t10, t11 = r10 * a + r11 * b, r10 * b + r11 * d
        out[j, 0, 0] = t00 * r00 + t01 * r01 + floor
        out[j, 0, 1] = t00 * r10 + t01 * r11
        out[j, 1, 0] = t10 * r00 + t11 * r01
        out[j, 1, 1] = t10 * r10 + t11 * r11 + floor
    return g, out


class _SampleTail:
    """:class:`_Tail` over the stride ``sample`` of particle rows ``(n, 2k)`` (a copy: the
    filter moves its particles in place) and its fit to the template, compiled."""

    def __init__(
        self, sample: FloatArray, k: int, ws: FloatArray, template: FloatArray, floor: float
    ) -> None:
        self.sample, self.k, self.ws, self.template, self.floor = sample, k, ws, template, floor

    def shape(self) -> tuple[FloatArray, FloatArray]:
        """As :meth:`_Tail.shape` (:func:`_shape_of`)."""
        return _shape_of(self.sample, self.k, self.ws, self.template, self.floor)

    def distances(self) -> FloatArray:
        """As :meth:`_Tail.distances`."""
        return _distances(self.sample, self.k, self.ws)


@compiled.njit(cache=True)
def _template(sample: FloatArray, k: int, ws: FloatArray) -> FloatArray:
    """The ``ws``-weighted mean of the sample's formations in the declared gauge
    (:func:`relloc.filter.gauge.gauge`: robot 0 on +x, robot 1 on the +y side), ``(k, 2)``."""
    out = np.zeros((k, 2))
    for i in range(sample.shape[0]):
        x0, y0 = sample[i, 0], sample[i, 1]
        r = math.hypot(x0, y0)
        c, s = (x0 / r, y0 / r) if r > 0.0 else (1.0, 0.0)
        flip = 1.0
        if k > 1 and c * sample[i, 3] - s * sample[i, 2] < 0.0:
            flip = -1.0
        for j in range(k):
            x, y = sample[i, 2 * j], sample[i, 2 * j + 1]
            out[j, 0] += ws[i] * (c * x + s * y)
            out[j, 1] += ws[i] * flip * (c * y - s * x)
    return out


@compiled.njit(cache=True, inline="always")
def _fit(row: FloatArray, k: int, template: FloatArray) -> tuple[float, float, float]:
    """The Procrustes fit of one formation to ``template``: cosine, sine and handedness
    (:func:`relloc.filter.gauge.procrustes_fit`)."""
    h00 = h01 = h10 = h11 = 0.0
    for j in range(k):
        x, y = row[2 * j], row[2 * j + 1]
        tx, ty = template[j, 0], template[j, 1]
        h00 += tx * x
        h01 += tx * y
        h10 += ty * x
        h11 += ty * y
    hand = -1.0 if k > 1 and h00 * h11 - h01 * h10 < 0.0 else 1.0
    c = h00 + hand * h11
    s = h01 - hand * h10
    norm = math.sqrt(c * c + s * s)
    if norm == 0.0:
        norm = 1.0
    return c / norm, s / norm, hand


@compiled.njit(cache=True, inline="always")
def _orientation_bin(c: float, s: float, hand: float, cos_edges: FloatArray) -> int:
    """The bin of :func:`_modes` of the angle ``atan2(s, c)`` and handedness ``hand``: on the
    upper half circle the count of inner edges at or before the angle (their cosines at or
    above ``c``) past the middle bin, on the lower half mirrored."""
    passed = 0
    for j in range(cos_edges.shape[0]):
        if cos_edges[j] >= c:
            passed += 1
    half = MODE_BINS // 2
    b = half + passed if s >= 0.0 else half - 1 - passed
    return b + MODE_BINS if hand < 0.0 else b


@compiled.njit(cache=True, inline="always")
def _add_moments(out: FloatArray, row: FloatArray, k: int, wi: float) -> None:
    """Add ``wi`` times ``x``, ``y``, ``x x``, ``y y``, ``x y`` of every robot of ``row`` to
    ``out`` (:func:`_planes` order)."""
    for j in range(k):
        x, y = row[2 * j], row[2 * j + 1]
        wx, wy = wi * x, wi * y
        out[j] += wx
        out[k + j] += wy
        out[2 * k + j] += wx * x
        out[3 * k + j] += wy * y
        out[4 * k + j] += wx * y


@compiled.njit(cache=True)
def _fit_and_bin(
    p: FloatArray,
    k: int,
    w: FloatArray,
    inv: float,
    template: FloatArray,
    cos_edges: FloatArray,
) -> tuple[IntArray, FloatArray, FloatArray]:
    """Per particle its orientation bin (:func:`_fit`, :func:`_orientation_bin`); per bin the
    sums over its particles (weights ``w * inv``) of the weight and the weighted cosine and
    sine of the fit ``(2 MODE_BINS, 3)``; and the weighted moments of all (:func:`_add_moments`)."""
    m = p.shape[0]
    cell = np.empty(m, dtype=np.intp)
    bins = np.zeros((2 * MODE_BINS, 3))
    sums = np.zeros(5 * k)
    for i in range(m):
        row = p[i]
        c, s, hand = _fit(row, k, template)
        b = _orientation_bin(c, s, hand, cos_edges)
        cell[i] = b
        wi = w[i] * inv
        bins[b, 0] += wi
        bins[b, 1] += wi * c
        bins[b, 2] += wi * s
        _add_moments(sums, row, k, wi)
    return cell, bins, sums


@compiled.njit(cache=True)
def _member_sums(
    p: FloatArray, k: int, w: FloatArray, scale: float, members: NDArray[np.bool_]
) -> FloatArray:
    """The moments (:func:`_add_moments`) of the ``members`` under weights ``w * scale``."""
    sums = np.zeros(5 * k)
    for i in range(p.shape[0]):
        if members[i]:
            _add_moments(sums, p[i], k, w[i] * scale)
    return sums


@compiled.njit(cache=True)
def _mode_labels(hist: FloatArray) -> tuple[IntArray, FloatArray]:
    """As :func:`_modes` from its histogram: each bin's mode label (-1: none; labels by
    decreasing weight, ties in the order the runs are found) and each mode's weight."""
    n = MODE_BINS
    heavy = hist > MODE_MIN_BIN_WEIGHT
    run_of = np.full(2 * n, -1, dtype=np.intp)
    weights = np.zeros(2 * n)
    runs = 0
    for h in range(2):
        occ = np.empty(n, dtype=np.bool_)
        for i in range(n):
            occ[i] = heavy[h * n + i] or heavy[h * n + (i - 1) % n] or heavy[h * n + (i + 1) % n]
        if not occ.any():
            continue
        if occ.all():
            for i in range(n):
                run_of[h * n + i] = runs
                weights[runs] += hist[h * n + i]
            runs += 1
            continue
        start = 0
        while occ[start]:
            start += 1
        open_run = False
        for j in range(1, n + 1):
            i = (start + j) % n
            if occ[i]:
                run_of[h * n + i] = runs
                weights[runs] += hist[h * n + i]
                open_run = True
            elif open_run:
                runs += 1
                open_run = False
        if open_run:
            runs += 1
    order = np.argsort(-weights[:runs], kind="mergesort")
    rank = np.empty(runs, dtype=np.intp)
    for r in range(runs):
        rank[order[r]] = r
    label = np.full(2 * n, -1, dtype=np.intp)
    for b in range(2 * n):
        if run_of[b] >= 0:
            label[b] = rank[run_of[b]]
    return label, weights[:runs][order]


@compiled.njit(cache=True)
def _shape_sums(sample: FloatArray, k: int, ws: FloatArray, template: FloatArray) -> FloatArray:
    """The ``ws``-weighted sums of ``x``, ``y``, ``x x``, ``y y``, ``x y`` (:func:`_planes`
    order) of the sample's formations turned onto the template (:func:`_fit`, :func:`_onto`)."""
    out = np.zeros(5 * k)
    for i in range(sample.shape[0]):
        wi = ws[i]
        c, s, hand = _fit(sample[i], k, template)
        for j in range(k):
            x, y = sample[i, 2 * j], sample[i, 2 * j + 1]
            ax = c * x + s * y
            ay = hand * (c * y - s * x)
            out[j] += wi * ax
            out[k + j] += wi * ay
            out[2 * k + j] += wi * ax * ax
            out[3 * k + j] += wi * ay * ay
            out[4 * k + j] += wi * ax * ay
    return out


@compiled.njit(cache=True)
def _distances(sample: FloatArray, k: int, ws: FloatArray) -> FloatArray:
    """Weighted mean and std of every pair's distance over the sample, ``(k+1, k+1, 2)``,
    the reference (the origin) index 0 (:meth:`_Tail.distances`)."""
    n = k + 1
    out = np.zeros((n, n, 2))
    mean = np.zeros((n, n))
    square = np.zeros((n, n))
    for i in range(sample.shape[0]):
        wi = ws[i]
        for a in range(n):
            ax = sample[i, 2 * (a - 1)] if a > 0 else 0.0
            ay = sample[i, 2 * (a - 1) + 1] if a > 0 else 0.0
            for b in range(a + 1, n):
                dx = ax - sample[i, 2 * (b - 1)]
                dy = ay - sample[i, 2 * (b - 1) + 1]
                dd = dx * dx + dy * dy
                mean[a, b] += wi * math.sqrt(dd)
                square[a, b] += wi * dd
    for a in range(n):
        for b in range(a + 1, n):
            std = math.sqrt(max(square[a, b] - mean[a, b] * mean[a, b], 0.0))
            out[a, b, 0] = out[b, a, 0] = mean[a, b]
            out[a, b, 1] = out[b, a, 1] = std
    return out


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
        cls, fields: tuple[Any, ...], members: NDArray[np.bool_], tail: _Tail | _SampleTail
    ) -> DeferredSummary:
        out = cls(*fields, None, None, None, members)  # type: ignore[call-arg]
        out.__dict__["_tail"] = tail
        return out

    def _materialize(self, name: str) -> None:
        tail: _Tail | _SampleTail = self.__dict__["_tail"]
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
