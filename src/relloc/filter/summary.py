"""An honest summary of a posterior over formations: its dominant mode, what is observable, and
the shape that is known even when the orientation is not.

Both filters hold ``M`` weighted hypotheses about the team's relative positions (particles, or
the means of Gaussians with their covariances). The weighted mean of all of them is a poor
estimate whenever the posterior has several modes: ranges alone cannot tell a formation from
its rotations about the reference robot or its mirror image, so a team at rest has a posterior
spread over a ring (two rings, one per handedness), and before motion has resolved them the
mirror images are separate modes. The mean of separated modes is a place where no mode is.

The method (:func:`summarize`), vectorised over hypotheses:

1. **Gauge.** Each hypothesis's formation ``P_m`` (``K`` robots x 2) is put in the declared
   gauge: turned about the reference so that the gauge robot (the first non-reference robot)
   lies on the reference's +x axis, then mirrored (``y -> -y``) if the next robot lies on the
   -y side. Two formations that differ only by a rotation/reflection about the reference have
   the same gauge form. The weighted mean of the gauge forms is a first template ``S``.
2. **Orientation and handedness** of every hypothesis relative to ``S`` by an orthogonal
   Procrustes (Kabsch) fit about the reference, which uses every robot, not only the gauge
   robot: with ``H = sum_k s_k p_k^T`` (2x2 per hypothesis) the best proper rotation has angle
   ``atan2(H01 - H10, H00 + H11)`` and the best reflection explains the formation better
   exactly when ``det H < 0`` (handedness ``-1``). With a single non-reference robot there is
   no handedness (``H`` has rank one): only the bearing's angle.
3. **Modes.** The angles are binned on the circle (``MODE_BINS`` bins, separately per
   handedness); the bins holding more than ``MODE_MIN_BIN_WEIGHT`` of the weight, and their
   neighbours (a mode's tails), are joined into circular runs, each run one mode. Hypotheses re-drawn from the prior (a percent of the
   cloud, spread over every bin) stay below the threshold. A ring is one run all round.
4. **Summary.** The dominant (heaviest) mode's weighted mean and covariance (for Gaussians,
   plus the members' own covariances), its weight, its angular spread and the number of modes
   are reported; the weighted mean of everything stays available as a diagnostic.
5. **Shape.** Every hypothesis is turned and mirrored onto ``S`` (its fit from step 2), the
   aligned formations averaged (a Procrustes mean, less noisy than the single-robot gauge),
   and the mean put back into the declared gauge exactly. Pairwise distances (reference
   included) are weighted moments over the hypotheses; they need no gauge.

Observability of the orientation is decided from both sides (:class:`Evidence`,
:func:`summarize`): the filter must have fused something that is not invariant under the
symmetry (a detection vector) or seen some robot move ``MOTION_TO_RESOLVE`` from where it
started, *and* the dominant mode's orientation must be concentrated (circular std below
``ORIENTATION_MAX_STD``). While nothing that could break the symmetry has been fused, the exact
posterior is invariant under rotations about the reference whatever the cloud looks like (a
cloud narrows by resampling alone, a hypothesis "hitchhiking" on the ancestors that fitted the
shape), so the published moments are those of the posterior symmetrised over the ring: mean at
the reference, covariance ``E|p|^2 / 2 I`` per robot. That covariance covers the truth (its
NEES is about 2 against a 95 % bound of 5.99) and the estimate says what it is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from relloc.events import pair_key
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


class Evidence:
    """What a filter has fused that can break the rotation/reflection symmetry: measurement
    models that are not invariant to it, and each robot's net odometry displacement."""

    def __init__(self, n_robots: int) -> None:
        self.non_invariant = 0
        self.offset = np.zeros((n_robots, 2))
        self.max_offset = 0.0

    def moved(self, disp: FloatArray) -> None:
        """Add one step's displacements ``(N, 2)``."""
        self.offset += np.nan_to_num(disp)
        self.max_offset = max(self.max_offset, float(np.max(np.hypot(self.offset[:, 0], self.offset[:, 1]))))

    def fused(self, models: Sequence[MeasurementModel]) -> None:
        self.non_invariant += sum(1 for m in models if not getattr(m, "invariant", True))

    def reset(self) -> None:
        """Forget the motion (the filter restarted from the symmetric start)."""
        self.offset[:] = 0.0
        self.max_offset = 0.0
        self.non_invariant = 0

    @property
    def can_resolve(self) -> bool:
        return self.non_invariant > 0 or self.max_offset >= MOTION_TO_RESOLVE


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


def estimate_fields(summary: ModeSummary, reference: str, others: Sequence[str]) -> dict[str, Any]:
    """The :class:`~relloc.estimate.Estimate` fields of ``summary`` (robots ``others`` in state
    order; pairs keyed by :func:`~relloc.events.pair_key`)."""
    names = (reference, *others)
    distances = {
        pair_key(a, b): (float(summary.distances[i, j, 0]), float(summary.distances[i, j, 1]))
        for i, a in enumerate(names)
        for j, b in enumerate(names)
        if j > i
    }
    return {
        "orientation_observable": summary.orientation_observable,
        "mode_weight": summary.mode_weight,
        "n_modes": summary.n_modes,
        "weighted_mean": {r: (float(summary.weighted_mean[k, 0]), float(summary.weighted_mean[k, 1])) for k, r in enumerate(others)},
        "shape": {r: (float(summary.shape[k, 0]), float(summary.shape[k, 1])) for k, r in enumerate(others)},
        "shape_gauge": others[0],
        "distances": distances,
    }


def gauge(rel: FloatArray) -> FloatArray:
    """Formations ``(M, K, 2)`` in the declared gauge: robot 0 on the +x axis, robot 1 (if any)
    on the +y side. Deterministic; a formation with robot 0 at the reference keeps its angle."""
    rel = np.asarray(rel, float)
    ang = np.arctan2(rel[:, 0, 1], rel[:, 0, 0])
    out = _rotate(rel, -ang)
    if rel.shape[1] > 1:
        flip = out[:, 1, 1] < 0.0
        out[flip, :, 1] *= -1.0
    return out


def _rotate(rel: FloatArray, theta: FloatArray) -> FloatArray:
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    x, y = rel[:, :, 0], rel[:, :, 1]
    return np.stack([c * x - s * y, s * x + c * y], axis=-1)


def procrustes_angles(rel: FloatArray, template: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Angle (rad) and handedness (+1/-1) of each formation ``(M, K, 2)`` relative to
    ``template`` ``(K, 2)``: formation ``m`` is best explained as ``template`` mirrored (if
    handedness is -1, ``y -> -y``) and then turned by the angle about the reference."""
    # H = sum_k t_k p_k^T per hypothesis; entries Hab = sum_k t_k[a] p_k[b].
    h00 = rel[:, :, 0] @ template[:, 0]
    h01 = rel[:, :, 1] @ template[:, 0]
    h10 = rel[:, :, 0] @ template[:, 1]
    h11 = rel[:, :, 1] @ template[:, 1]
    det = h00 * h11 - h01 * h10
    hand = np.where(det < -1e-12 * (np.abs(h00 * h11) + np.abs(h01 * h10) + 1e-300), -1.0, 1.0)
    # proper: p = R(a) t  -> a = atan2(h01 - h10, h00 + h11); mirrored: p = R(a) F t, F = diag(1, -1)
    proper = np.arctan2(h01 - h10, h00 + h11)
    mirrored = np.arctan2(h01 + h10, h00 - h11)
    return np.where(hand > 0, proper, mirrored), hand


def _modes(angle: FloatArray, hand: FloatArray, w: FloatArray) -> IntArray:
    """Mode label of every hypothesis (-1: in no mode), labels ordered by decreasing weight."""
    b = np.floor((angle + np.pi) / (2.0 * np.pi) * MODE_BINS).astype(np.intp) % MODE_BINS
    cell = b + np.where(hand < 0, MODE_BINS, 0)
    hist = np.bincount(cell, weights=w, minlength=2 * MODE_BINS)
    label_of_cell = np.full(2 * MODE_BINS, -1, dtype=np.intp)
    runs: list[list[int]] = []
    for h in range(2):
        occ = hist[h * MODE_BINS : (h + 1) * MODE_BINS] > MODE_MIN_BIN_WEIGHT
        occ = occ | np.roll(occ, 1) | np.roll(occ, -1)  # a mode's tails: its neighbour bins
        if not occ.any():
            continue
        if occ.all():
            runs.append([h * MODE_BINS + i for i in range(MODE_BINS)])
            continue
        start = int(np.flatnonzero(~occ)[0])  # walk the circle from an empty bin
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
    runs.sort(key=lambda r: -float(hist[r].sum()))
    for k, run in enumerate(runs):
        label_of_cell[run] = k
    return label_of_cell[cell]


def _moments(x: FloatArray, w: FloatArray, covs: FloatArray | None) -> tuple[FloatArray, FloatArray]:
    """Weighted mean ``(K, 2)`` and per-robot covariance ``(K, 2, 2)`` of ``x`` ``(M, K, 2)``
    (plus the weighted member covariances ``covs`` ``(M, K, 2, 2)``, if any)."""
    sw = float(w.sum())
    wn = w / sw if sw > 0 else np.full(w.shape, 1.0 / w.size)
    mean = np.einsum("m,mkd->kd", wn, x)
    c = x - mean
    cov = np.einsum("m,mka,mkb->kab", wn, c, c)
    if covs is not None:
        cov = cov + np.einsum("m,mkab->kab", wn, covs)
    return mean, cov


def summarize(
    rel: FloatArray,
    w: FloatArray,
    covs: FloatArray | None = None,
    *,
    can_resolve: bool = True,
) -> ModeSummary:
    """The honest summary of hypotheses ``rel`` ``(M, K, 2)`` (relative positions of the
    non-reference robots) with normalised weights ``w`` ``(M,)`` and, for Gaussians, their
    per-robot position covariances ``covs`` ``(M, K, 2, 2)``. ``can_resolve``: whether what was
    fused could have broken the rotation/reflection symmetry (:class:`Evidence`)."""
    rel = np.asarray(rel, float)
    w = np.asarray(w, float)
    w = w / w.sum() if w.sum() > 0 else np.full(w.shape, 1.0 / w.size)
    m, k, _ = rel.shape
    weighted_mean, _ = _moments(rel, w, covs)

    template = np.einsum("m,mkd->kd", w, gauge(rel))
    angle, hand = procrustes_angles(rel, template)
    if k == 1:
        hand = np.ones(m)
    labels = _modes(angle, hand, w)
    members = labels == 0 if (labels >= 0).any() else np.ones(m, dtype=bool)
    mode_w = np.bincount(labels[labels >= 0], weights=w[labels >= 0])
    n_modes = max(1, int(np.sum(mode_w >= MODE_MIN_WEIGHT)))
    mode_weight = float(w[members].sum())

    # Refine the template on the dominant mode (its members put onto the template), then the
    # members' angles about it: the mode's circular spread.
    aligned = _rotate(rel, -angle)
    aligned[hand < 0, :, 1] *= -1.0
    template = np.einsum("m,mkd->kd", w * members, aligned) / max(mode_weight, 1e-300)
    angle, hand = procrustes_angles(rel, template)
    if k == 1:
        hand = np.ones(m)
    wm = w * members
    wm = wm / wm.sum()
    rbar = math.hypot(float(wm @ np.cos(angle)), float(wm @ np.sin(angle)))
    orientation_std = math.pi if rbar <= math.exp(-0.5 * math.pi**2) else min(math.sqrt(-2.0 * math.log(rbar)), math.pi)

    mode_mean, mode_cov = _moments(rel[members], w[members], None if covs is None else covs[members])

    if can_resolve:
        mean, cov = mode_mean, mode_cov
    else:
        # The exact posterior is invariant under rotations about the reference: its moments.
        r2 = np.einsum("m,mk->k", w, np.sum(rel * rel, axis=2))
        if covs is not None:
            r2 = r2 + np.einsum("m,mk->k", w, np.trace(covs, axis1=2, axis2=3))
        mean = np.zeros((k, 2))
        cov = 0.5 * r2[:, None, None] * np.eye(2)[None]

    # Shape: every hypothesis put onto the template, averaged, then into the declared gauge.
    aligned = _rotate(rel, -angle)
    aligned[hand < 0, :, 1] *= -1.0
    shape_mean, shape_cov = _moments(aligned, w, covs)
    g = gauge(shape_mean[None])[0]
    # The same rotation/reflection for the covariance.
    a0 = math.atan2(shape_mean[0, 1], shape_mean[0, 0])
    rot = np.array([[math.cos(-a0), -math.sin(-a0)], [math.sin(-a0), math.cos(-a0)]])
    if k > 1 and (rot @ shape_mean[1])[1] < 0.0:
        rot = np.diag([1.0, -1.0]) @ rot
    shape_cov = np.einsum("ab,kbc,dc->kad", rot, shape_cov, rot)

    pts = np.concatenate([np.zeros((m, 1, 2)), rel], axis=1)  # reference first
    d = np.sqrt(np.sum((pts[:, :, None, :] - pts[:, None, :, :]) ** 2, axis=-1))  # (M, K+1, K+1)
    dmean = np.einsum("m,mij->ij", w, d)
    dstd = np.sqrt(np.maximum(np.einsum("m,mij->ij", w, d * d) - dmean**2, 0.0))

    return ModeSummary(
        mean=mean,
        cov=cov,
        weighted_mean=weighted_mean,
        mode_weight=mode_weight,
        n_modes=n_modes,
        orientation_std=orientation_std,
        orientation_observable=bool(can_resolve and orientation_std < ORIENTATION_MAX_STD),
        shape=g,
        shape_cov=shape_cov,
        distances=np.stack([dmean, dstd], axis=-1),
        members=members,
    )
