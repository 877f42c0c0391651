"""Measurement models: what a sensor tells every estimator kind, in one protocol.

A model serves the particle filter (``log_likelihood`` over all particles), the Gaussian sums
(``rows``/``row``: the measurement linearised at each Gaussian's mean) and the smoother
(``fixes``: relative positions as factors, :mod:`relloc.filter.factors`), so that a sensor is
one class whatever runs it (navlie's pattern). The derivation: docs/explanation/internals.md,
section ``relloc.filter.measurement``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from relloc.config import TeamConfig
    from relloc.filter.factors import RelativeFix
    from relloc.filter.state import TeamLayout

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


@dataclass(frozen=True)
class ModelContext:
    """What a model needs to build itself for one filter: the team's configuration, the
    filter's state layout (robot indices, and how its state holds online range biases) and
    which likelihood to build."""

    config: TeamConfig
    layout: TeamLayout
    robust: bool = True
    """False: the plain Gaussian likelihood without the outlier floor (the guide that the
    annealed start tempers, :meth:`relloc.estimators.particle.filter.ParticleFilter.initialize_annealed`)."""
    range_model: str = "nlos"
    """``nlos`` or ``symmetric`` (:class:`relloc.config.FilterConfig`): which range likelihood
    the localizer's filter uses."""
    yaws: Mapping[str, float] | None = None
    """Each robot's odometry yaw (rad) at the batch time, in the frame of its odometry track:
    the shared heading frame where the filter has one, the robot's own odometry frame where
    the filter estimates the headings. Models of measurements in a robot's body frame (a
    sighting's bearing) turn them with it; ``None``: not known (such a model falls back to
    what needs no heading)."""
    shared_heading: bool = True
    """Whether the localizer's filter works in a shared (compass) heading frame."""
    yaw_at: Callable[[str, float], float] | None = None
    """A robot's odometry yaw (rad, shared heading frame) at any time, NaN where unknown: what
    a factor graph's model turns an event's body-frame measurement with at the event's own
    time (:meth:`MeasurementModel.fixes`); ``None``: not known."""


class ValidationContext(Protocol):
    """What a model's validation rule may ask of the localizer."""

    config: TeamConfig

    @property
    def layout(self) -> TeamLayout: ...

    def is_late(self, t: float) -> bool:
        """Whether a measurement stamped ``t`` comes after the filter has moved past it."""
        ...

    def memory(self, model: type) -> dict[Any, Any]:
        """A dictionary the rule of ``model`` may keep state in (e.g. the last value per pair)."""
        ...


@dataclass(frozen=True)
class LinearRow:
    """One scalar measurement linearised at every Gaussian's mean: ``z ~ h x + r`` with
    ``h`` nonzero only in ``columns``, innovation ``residual = z - prediction(mean)`` and
    measurement-noise ``variance``. The density of the innovation is Gaussian-plus-uniform:
    ``(1 - eps) N(r; 0, s) + eps / support`` (``s`` the predictive variance), whose inlier
    probability scales the Kalman gain, so an outlier barely moves the state."""

    columns: IntArray  # (c,)
    jacobian: FloatArray  # (M, c)
    residual: FloatArray  # (M,)
    variance: float
    outlier_fraction: float = 0.0
    support: float = 1.0

    def density(self, residual: FloatArray, s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Log predictive density and inlier probability of ``residual`` with predictive
        variance ``s`` (both ``(M,)``)."""
        return robust_gaussian(residual, s, self.outlier_fraction, self.support)


def robust_gaussian(
    residual: FloatArray, s: FloatArray, eps: float, support: float
) -> tuple[FloatArray, FloatArray]:
    """``log((1 - eps) N(residual; 0, s) + eps / support)`` and the probability that the
    measurement is an inlier (1 where ``eps`` is 0), elementwise."""
    z2 = residual * residual / s
    gauss = np.exp(-0.5 * z2) / np.sqrt(2.0 * np.pi * s)
    if eps > 0.0:
        dens = (1.0 - eps) * gauss + eps / support
        return np.log(dens), (1.0 - eps) * gauss / dens
    return -0.5 * z2 - 0.5 * np.log(s) - _LOG_SQRT_2PI, np.ones_like(s)


class MeasurementModel(Protocol):
    """The protocol of every measurement model (module docstring)."""

    events: ClassVar[tuple[type, ...]]
    stat: ClassVar[str]
    """Name under which the localizer counts the accepted events."""
    invariant: ClassVar[bool]
    needs_shared_heading: ClassVar[bool]

    @classmethod
    def build(cls, events: Sequence[Any], context: ModelContext) -> list[MeasurementModel]: ...

    @classmethod
    def rejection(cls, event: Any, context: ValidationContext) -> str | None: ...

    def log_likelihood(self, positions: FloatArray, particles: FloatArray) -> FloatArray: ...

    @property
    def rows(self) -> int: ...

    def row(self, k: int, mean: FloatArray) -> LinearRow: ...

    @property
    def conditions(self) -> bool: ...

    def condition(self, positions: FloatArray, particles: FloatArray) -> None: ...

    ranged: ClassVar[bool] = False
    """Whether the robots an event is news of (:meth:`heard`) count as ranged."""

    @classmethod
    def stream(cls, event: Any) -> tuple[str, ...]:
        """Which stream ``event`` belongs to: one per event type and robot (or observer)."""
        return (type(event).__name__, str(getattr(event, "robot", getattr(event, "observer", ""))))

    @classmethod
    def heard(cls, event: Any) -> tuple[str, ...]:
        """The robots ``event`` is news of (their position): none by default."""
        return ()

    @classmethod
    def fixes(
        cls, events: Sequence[Any], context: ModelContext
    ) -> tuple[list[RelativeFix], int] | None:
        """What a factor graph (the smoother) takes of ``events``: measured relative positions
        (:class:`relloc.filter.factors.RelativeFix`) and how many events gave none. ``None``
        (the default): this model offers no factors, and a factor-graph kind counts its events
        unused."""
        return None


def hook(model: type[MeasurementModel], name: str) -> Any:
    """``model``'s optional hook ``name`` (``stream``, ``heard``, ``ranged``), or the
    protocol's default where the model follows the protocol without defining it."""
    return getattr(model, name, getattr(MeasurementModel, name))


def stacked(models: Sequence[MeasurementModel]) -> Callable[[FloatArray, FloatArray], FloatArray]:
    """The log-likelihood of everything that arrived in one batch, fused as one measurement
    (the paper's stacked measurement vector): the models' log-likelihoods add up."""
    first, rest = models[0], models[1:]

    def log_likelihood(positions: FloatArray, particles: FloatArray) -> FloatArray:
        total = first.log_likelihood(positions, particles)
        for model in rest:
            total = total + model.log_likelihood(positions, particles)
        return total

    return log_likelihood


def finite(x: object) -> bool:
    """A finite real number (not a bool, a string or an array): what every event field must be."""
    if type(x) is float:  # the common case, without the ABC check (several per event, live)
        return math.isfinite(x)
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x)
