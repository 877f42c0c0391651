"""The relative-position model: measured vectors ``p_target - p_observer`` between robots.

Produced by cooperative detections: two robots see one object at once, and ``R_i o_i - R_j o_j``
gives ``p_j - p_i`` in the shared heading frame (:mod:`relloc.stages.association`). Each vector
has an isotropic Gaussian error of ``sigma`` per axis, mixed with a small uniform floor over
``support`` square metres for a wrong association::

    p(v) = (1 - eps) N(v; p_t - p_o, sigma^2 I) + eps / support

Unlike a range, a vector fixes the formation's orientation: the model is not invariant to a
rotation or reflection about the reference, and it needs the shared heading frame (a filter
that estimates the headings has none). The Gaussian-sum filter fuses it as two scalar rows, one
per axis, each with the square root of the support.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from relloc.events import RelativeObservation
from relloc.filter.factors import RelativeFix
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

OUTLIER_FRACTION = 0.02
"""Weight of the uniform part: the share of wrong associations the gate lets through."""


@dataclass(frozen=True)
class RelativePositionBatch(MeasurementModel):
    """``K`` measured vectors ``p_target - p_observer`` in the shared heading frame."""

    events: ClassVar[tuple[type, ...]] = (RelativeObservation,)
    stat: ClassVar[str] = "relative"
    invariant: ClassVar[bool] = False
    needs_shared_heading: ClassVar[bool] = True

    index_observer: IntArray
    index_target: IntArray
    vector: FloatArray  # (K, 2)
    sigma: FloatArray  # (K,), per axis
    outlier_fraction: float = OUTLIER_FRACTION
    support: float = 100.0  # area (m^2) of the uniform outlier density
    layout: TeamLayout | None = None
    """The state layout the vectors index (needed by :meth:`row` only)."""

    def __len__(self) -> int:
        return len(self.sigma)

    @classmethod
    def build(
        cls, events: Sequence[RelativeObservation], context: ModelContext
    ) -> list[MeasurementModel]:
        if not events:
            return []
        layout = context.layout
        return [
            cls(
                np.array([layout.index(v.observer) for v in events], dtype=np.intp),
                np.array([layout.index(v.target) for v in events], dtype=np.intp),
                np.array([v.vector for v in events], dtype=float),
                np.array([v.sigma for v in events]),
                outlier_fraction=OUTLIER_FRACTION if context.robust else 0.0,
                layout=layout,
            )
        ]

    @classmethod
    def heard(cls, event: RelativeObservation) -> tuple[str, ...]:
        return (event.observer, event.target)

    @classmethod
    def fixes(
        cls, events: Sequence[RelativeObservation], context: ModelContext
    ) -> tuple[list[RelativeFix], int]:
        """Each observation as it is: ``(dx, dy)`` with ``sigma`` per axis."""
        index = context.layout.index
        return [
            RelativeFix(
                index(v.observer),
                index(v.target),
                np.array(v.vector, dtype=float),
                v.sigma**2 * np.eye(len(v.vector)),
            )
            for v in events
        ], 0

    @classmethod
    def rejection(cls, event: RelativeObservation, context: ValidationContext) -> str | None:
        names = context.layout.robots
        if event.observer not in names or event.target not in names:
            return "unknown_robot"
        if event.observer == event.target:
            return "self_observation"
        if (
            len(event.vector) != 2  # the filters' positions are planar
            or not all(map(finite, (*event.vector, event.sigma)))
            or event.sigma <= 0
        ):
            return "invalid_relative_observation"
        if context.is_late(event.t):
            return "late_measurement"
        return None

    def log_likelihood(
        self, positions: FloatArray, particles: FloatArray | None = None
    ) -> FloatArray:
        ex = (
            positions[0, self.index_target]
            - positions[0, self.index_observer]
            - self.vector[:, 0:1]
        )
        ey = (
            positions[1, self.index_target]
            - positions[1, self.index_observer]
            - self.vector[:, 1:2]
        )
        s2 = (self.sigma**2)[:, None]
        r2 = ex * ex + ey * ey  # (K, M)
        eps = self.outlier_fraction
        if eps <= 0.0:
            return (-0.5 * r2 / s2 - np.log(2.0 * np.pi * s2)).sum(axis=0)
        dens = (1.0 - eps) / (2.0 * np.pi * s2) * np.exp(-0.5 * r2 / s2) + eps / self.support
        return np.log(dens).sum(axis=0)

    conditions: ClassVar[bool] = False

    def condition(self, positions: FloatArray, particles: FloatArray) -> None:
        """No sufficient statistics in the state."""

    @property
    def rows(self) -> int:
        return 2 * len(self.sigma)

    def row(self, k: int, mean: FloatArray) -> LinearRow:
        """Axis ``k % 2`` of vector ``k // 2``: ``+1`` on the target's column, ``-1`` on the
        observer's (the reference has none)."""
        if self.layout is None:
            raise ValueError("a relative-position model needs its layout to be linearised")
        j, axis = divmod(k, 2)
        n = mean.shape[0]
        so = self.layout.slot_of(int(self.index_observer[j]))
        st = self.layout.slot_of(int(self.index_target[j]))
        cols, coefs = [], []
        pred = np.zeros(n)
        if st >= 0:
            cols.append(2 * st + axis)
            coefs.append(np.ones(n))
            pred = pred + mean[:, 2 * st + axis]
        if so >= 0:
            cols.append(2 * so + axis)
            coefs.append(-np.ones(n))
            pred = pred - mean[:, 2 * so + axis]
        return LinearRow(
            np.array(cols),
            np.stack(coefs, axis=1),
            float(self.vector[j, axis]) - pred,
            float(self.sigma[j]) ** 2,
            self.outlier_fraction,
            math.sqrt(self.support),
        )
