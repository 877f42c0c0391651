"""Measurement models: what a sensor tells the filters, in one protocol both filters call.

A measurement model is an immutable batch of measurements of one kind (all the ranges of one
update, all the detection vectors, ...) that knows everything sensor-specific, so that neither
filter nor any localizer does:

``events`` (class)
    The event types it is built from; :mod:`relloc.filter.registry` maps each to its model.
``build(events, context)`` (class)
    The models of one batch of those events (a list: one kind of event may need two
    likelihoods, e.g. raw and learned-corrected ranges), for the state layout of the filter
    that will fuse them (:class:`ModelContext`).
``rejection(event, context)`` (class)
    Its validation rule: the counted reason a bad event is dropped, or ``None``.
``log_likelihood(positions, particles)``
    ``log p(z | x)`` of every particle: the sampled filter's update. ``positions`` holds the
    robots' relative positions as coordinate planes ``(2, N, M)``
    (:meth:`~relloc.filter.state.StateLayout.positions`), ``particles`` the rows ``(M, D)``
    themselves (for state blocks beyond the positions).
``rows`` and ``row(k, mean)``
    Its linearisation for the Gaussian-sum filter: scalar measurement rows
    (:class:`LinearRow`), each linearised at the current means ``(M, D)``, fused one after
    the other by the filter's one robust scalar Kalman step.
``condition(positions, particles)``
    After the sampled filter has re-weighted its particles, update any sufficient statistics
    the model owns in the state (the online range bias's per-particle Kalman filter); most
    models have none (``conditions`` False).
``invariant`` (class)
    Whether its likelihood is unchanged when the whole formation is rotated about the
    reference or mirrored. The annealed start anneals on the invariant models only, spreads
    the result over those symmetries (exact for an invariant target) and then weighs by the
    others; with no invariant model it anneals on everything and does not spread.
``needs_shared_heading`` (class)
    Whether the measurement is expressed in the team's shared (compass) heading frame: a
    filter that estimates the headings has no such frame and cannot fuse it.
``stream(event)``, ``heard(event)``, ``ranged`` (class, optional)
    What the localizer's bookkeeping reads of an event: the stream it belongs to (the team
    clock's warm-up and jump votes count streams), the robots it is news of (the unseen-robot
    rule) and whether those count as ranged (the orientation kernel waits while a robot is
    not). A model that follows the protocol without subclassing it may leave them out:
    :func:`hook` then reads the protocol's defaults (one stream per event type and robot,
    news of nobody, not ranged).

The linearisation and the likelihood are two views of one model; the test suite checks every
registered model's rows against finite differences of its log-likelihood.
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
    annealed start tempers, :meth:`relloc.filter.pf.ParticleFilter.initialize_annealed`)."""
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


def robust_gaussian(residual: FloatArray, s: FloatArray, eps: float, support: float) -> tuple[FloatArray, FloatArray]:
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
