"""The one interface of relloc's filters, and what they share.

The derivation: docs/explanation/internals.md, section ``relloc.filter.base``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from relloc.filter.measurement import MeasurementModel
from relloc.filter.motion import PriorBox
from relloc.filter.resampling import ess, log_normalize, reinjection_slots, systematic_resample
from relloc.filter.state import TeamLayout
from relloc.filter.summary import ModeSummary

if TYPE_CHECKING:
    from relloc.filter.annealing import StartContext

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

RESAMPLE_MODES = ("ess", "every_step")
ESS_THRESHOLD = 0.5
"""Resample (mode ``ess``) when the effective sample size falls below this fraction of the
count: the usual half, a resampling only once the weights have degenerated."""
REINJECT_FRACTION = 0.01
"""Fraction of the hypotheses re-drawn from the prior at each resampling, so that a filter on
a wrong mode can recover (the paper's 1 %)."""


@dataclass(frozen=True)
class FilterEstimate:
    """Weighted moments of a filter: each non-reference robot's relative position and, where
    the filter estimates them, headings, range biases and odometry scales (mean, std)."""

    mean: FloatArray  # (N-1, 2)
    cov: FloatArray  # (N-1, 2, 2)
    ess: float | None
    """Effective sample size of the weights (``None``: the estimator has no weighted
    hypotheses, the smoother)."""
    headings: dict[str, tuple[float, float]] = field(default_factory=dict)
    biases: dict[str, tuple[float, float]] = field(default_factory=dict)
    scales: dict[str, tuple[float, float]] = field(default_factory=dict)
    summary: ModeSummary | None = None
    """The dominant mode, observability and shape (:mod:`relloc.filter.summary`); ``mean`` and
    ``cov`` are then its published moments."""
    particles: int | None = None
    """Hypotheses the filter holds (an adaptive particle count changes it at resampling)."""
    yaws: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Robots whose tags show their heading: each one's heading relative to the reference's."""
    offsets: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Shared offsets of the online biases (team, nodes: :class:`~relloc.localizers.priors.BiasPrior`)
    where the estimator keeps them apart (the smoother)."""


def renormalized(logw: FloatArray) -> FloatArray | None:
    """Log-weights normalised (non-finite ones to ``-inf``), or ``None`` when none is finite:
    no hypothesis explains the measurements, and the caller keeps its weights."""
    finite = np.isfinite(logw)
    if not finite.any():
        return None
    return log_normalize(logw if finite.all() else np.where(finite, logw, -np.inf))


class WeightedFilter:
    """Log-weights, the resampling schedule and re-injection from the uniform prior box."""

    layout: TeamLayout

    def __init__(
        self,
        n: int,
        area: tuple[float, float, float, float],
        *,
        rng: np.random.Generator,
        resample: str = "ess",
        ess_threshold: float = ESS_THRESHOLD,
        reinject_fraction: float = REINJECT_FRACTION,
    ) -> None:
        if n < 1:
            raise ValueError("n_particles must be positive")
        if resample not in RESAMPLE_MODES:
            raise ValueError(f"resample must be 'ess' or 'every_step', got {resample!r}")
        if not 0.0 <= reinject_fraction < 1.0:
            raise ValueError("reinject_fraction must be in [0, 1)")
        self.n = n
        self.rng = rng
        self.prior = PriorBox(area)
        self.half_extent = self.prior.half_extent
        self.resample_mode = resample
        self.ess_threshold = ess_threshold
        self.reinject_fraction = reinject_fraction
        self.logw = np.full(n, -math.log(n))
        self.resample_count = 0

    # ---------------------------------------------------------------- the cycle
    def predict(self, disp: FloatArray, sigma: FloatArray, dt: float) -> None:
        raise NotImplementedError

    def update(self, models: Sequence[MeasurementModel]) -> bool:
        raise NotImplementedError

    def estimate(self) -> FilterEstimate:
        raise NotImplementedError

    def body_estimate(self, reference_yaw: float) -> FilterEstimate | None:
        """The estimate in the reference robot's body frame, where the filter's own frame is
        one the measurements do not observe (the reference's drifting odometry frame); ``None``
        where it is the compass's shared heading frame, which they do."""
        return None

    @property
    def shared_heading(self) -> bool:
        """Whether the state is in the team's shared heading frame (measurements expressed in
        it, such as detection vectors, can be fused)."""
        return True

    def counters(self) -> dict[str, int]:
        """Running counts of the filter's own events, for the localizer's statistics."""
        return {}

    # ---------------------------------------------------------------- recovery hooks
    def restart(
        self, recent: list[Any], reference: FloatArray | None, context: StartContext
    ) -> bool:
        """Start again from ``recent`` (the measurements since the filter got lost), oriented
        by the ``reference`` formation (relative positions ``(2(N-1),)``; ``None``: none
        trusted), the models built by ``context``; False if the filter cannot (this default:
        the localizer then re-injects hypotheses, :meth:`inject`)."""
        return False

    def pause_kernel(self, paused: bool) -> None:
        """Whether some robot is out of ranging (the formation is then not one rigid body):
        for a filter that moves the formation's orientation on its own; nothing here."""

    # ---------------------------------------------------------------- resampling
    def ess(self) -> float:
        return ess(self.logw)

    def maybe_resample(self) -> bool:
        """Resample if configured to (every step, or ESS below threshold); True if it did."""
        if self.resample_mode == "ess" and self.ess() >= self.ess_threshold * self.n:
            return False
        self.resample()
        return True

    def resample(self) -> None:
        """Systematic resampling (to the size :meth:`_resampled_size` asks for: the same, but
        for an adaptive particle count), then a ``reinject_fraction`` of the slots re-drawn
        from the prior box; equal weights."""
        w = self._exp_logw()
        idx = systematic_resample(w, self.rng)
        n = self._resampled_size(idx)
        if n != self.n:
            idx = systematic_resample(w, self.rng, n)
            self.n = n
        self._select(idx)
        self._finish_resample()

    def _finish_resample(self) -> None:
        """After the rows are drawn: a ``reinject_fraction`` of the slots re-drawn from the
        prior box, equal weights, the count and the hook; every resampling path ends here."""
        slots = reinjection_slots(self.n, self.reinject_fraction, self.rng)
        if slots.size:
            self._reinject(slots, self.prior.sample(self.rng, slots.size, self.layout.n_others))
        self.logw = np.full(self.n, -math.log(self.n))
        self.resample_count += 1
        self._after_resample()

    def inject(self, formations: FloatArray) -> IntArray:
        """Recovery: resample, then restart ``len(formations)`` hypotheses, chosen at random,
        at the given formations (relative positions ``(K, 2(N-1))``, further state at its
        prior); equal weights. What a localizer calls when it finds the filter lost: the
        measurements then weigh the injected hypotheses against the kept ones. A filter with
        an adaptive count first grows back to its full count (:meth:`_recovery_size`), the
        formations repeated so that they keep their share. Returns the slots re-drawn."""
        n = self._recovery_size()
        formations = np.asarray(formations, dtype=float)
        if n != self.n and len(formations):
            # The count grows back (an adaptive filter): the injected share stays the same,
            # the given formations repeated.
            formations = np.resize(
                formations, (round(len(formations) * n / self.n), formations.shape[1])
            )
        self.n = n
        k = min(len(formations), self.n)
        self._select(systematic_resample(self._exp_logw(), self.rng, self.n))
        slots = self.rng.choice(self.n, size=k, replace=False).astype(np.intp)
        self._reinject(slots, np.asarray(formations[:k], dtype=float))
        self.logw = np.full(self.n, -math.log(self.n))
        self.resample_count += 1
        return slots

    def _exp_logw(self) -> FloatArray:
        """``exp`` of the log-weights (normalised by :meth:`update`): what resampling draws by."""
        return np.exp(self.logw)

    def _resampled_size(self, idx: IntArray) -> int:
        """How many hypotheses a resampling keeps, given the systematic draw ``idx`` at the
        present count (the present count; an adaptive filter's rule)."""
        return self.n

    def _recovery_size(self) -> int:
        """How many hypotheses :meth:`inject` resamples to (the present count; an adaptive
        filter grows back to its full count)."""
        return self.n

    def _select(self, idx: IntArray) -> None:
        """Keep hypotheses ``idx`` (with repetitions), in that order."""
        raise NotImplementedError

    def _reinject(self, slots: IntArray, positions: FloatArray) -> None:
        """Restart the hypotheses in ``slots`` at the prior, at formations ``positions``."""
        raise NotImplementedError

    def _after_resample(self) -> None:
        """A filter's own step after each resampling (none by default)."""
