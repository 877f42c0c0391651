"""The sighting model: a teammate seen in the observer's body frame, at a range and a bearing.

A camera that reads a teammate's marker, or a UWB radio with angle of arrival, measures where
robot ``j`` is as robot ``i`` sees it: a range ``r`` and a bearing ``b`` (counter-clockwise from
``i``'s forward axis), both or one of them. With ``v = p_j - p_i`` in the filter's frame and
``psi_i`` the observer's heading in that frame::

    r = |v| + n_r,          b = atan2(v_y, v_x) - psi_i + n_b   (wrapped to (-pi, pi])

each with a Gaussian-plus-uniform density (a misread marker, a reflection):
``(1 - eps) N(res; 0, sigma^2) + eps / support``, the bearing's residual wrapped at +-pi before
it is scored (a bearing of 179 deg and a prediction of -179 deg are 2 deg apart), its floor
uniform over the circle.

The derivation: docs/explanation/internals.md, section ``relloc.filter.sightings``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from relloc.events import SightingEvent
from relloc.filter.factors import RelativeFix
from relloc.filter.measurement import (
    LinearRow,
    MeasurementModel,
    ModelContext,
    ValidationContext,
    finite,
    robust_gaussian,
)
from relloc.filter.state import TeamLayout

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

OUTLIER_FRACTION = 0.02
"""Weight of the uniform floor of every row: misread markers, reflections, a wrong robot."""
MAX_RANGE = 15.0
"""Support (m) of the uniform floor of ranges and of the along/cross rows."""

KINDS = ("range", "bearing", "along", "cross_unit")


def wrap(angle: FloatArray | float) -> FloatArray:
    """``angle`` wrapped to ``[-pi, pi)``, elementwise."""
    return np.remainder(np.asarray(angle, float) + math.pi, 2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class _Row:
    """One scalar row of a sighting: which kind (module docstring), the sighting's robots and
    its measured value, noise, and the direction ``w`` (heading mode)."""

    kind: str
    observer: int
    target: int
    z: float
    variance: float
    psi: float = 0.0
    """Compass: the observer's heading in the shared frame (bearing rows)."""
    w: tuple[float, float] = (1.0, 0.0)
    """Heading mode: the measured direction in the observer's odometry frame."""
    support: float = MAX_RANGE


@dataclass(frozen=True)
class SightingBatch(MeasurementModel):
    """The sightings of one batch as scalar rows, for one filter's state layout."""

    events: ClassVar[tuple[type, ...]] = (SightingEvent,)
    stat: ClassVar[str] = "sighting"
    invariant: ClassVar[bool] = False
    invariant_without_shared_heading: ClassVar[bool] = True
    """Built for a filter with no heading at all (a sampled start under heading estimation)
    the model is ranges only, which a rotation or reflection of the formation leaves
    unchanged: the annealed start may spread over those symmetries."""
    needs_shared_heading: ClassVar[bool] = False
    conditions: ClassVar[bool] = False

    layout: TeamLayout
    items: tuple[_Row, ...]
    outlier_fraction: float = OUTLIER_FRACTION
    u_columns: dict[int, tuple[int, int]] = field(default_factory=dict)
    """Heading mode: the state columns of each observer's ``u`` (team index -> columns)."""

    def __len__(self) -> int:
        return len(self.items)

    # ---------------------------------------------------------------- building, validation
    @classmethod
    def fixes(
        cls, events: Sequence[SightingEvent], context: ModelContext
    ) -> tuple[list[RelativeFix], int]:
        """The sightings with a range and a bearing whose observer's yaw (at the sighting's
        time, ``context.yaw_at``) is known: ``r (cos a, sin a)``, ``a`` the yaw plus the
        bearing, radial std the range's, tangential ``r`` times the bearing's. The others are
        counted: one range or one bearing alone does not fix a relative position."""
        out: list[RelativeFix] = []
        unused = 0
        index = context.layout.index
        for m in events:
            yaw = (
                context.yaw_at(m.observer, m.t)
                if m.bearing is not None and context.yaw_at is not None
                else math.nan
            )
            if m.range is None or m.bearing is None or not math.isfinite(yaw):
                unused += 1
                continue
            a = yaw + m.bearing
            u = np.array([math.cos(a), math.sin(a)])
            w = np.array([-u[1], u[0]])
            cov = m.sigma_range**2 * np.outer(u, u) + (m.range * m.sigma_bearing) ** 2 * np.outer(
                w, w
            )
            out.append(
                RelativeFix(index(m.observer), index(m.target), m.range * u, cov + 1e-8 * np.eye(2))
            )
        return out, unused

    @classmethod
    def build(
        cls, events: Sequence[SightingEvent], context: ModelContext
    ) -> list[MeasurementModel]:
        """The rows of ``events`` for ``context``'s filter: heading mode where the layout
        estimates headings, compass where the filter has a shared frame and the observers'
        yaws are known, ranges only otherwise."""
        if not events:
            return []
        layout = context.layout
        yaws = context.yaws or {}
        heading = bool(getattr(layout, "heading", False))
        compass = not heading and context.shared_heading and context.yaws is not None
        rows: list[_Row] = []
        ucols: dict[int, tuple[int, int]] = {}
        for ev in events:
            i, j = layout.index(ev.observer), layout.index(ev.target)
            yaw = yaws.get(ev.observer, math.nan)
            has_r = ev.range is not None
            has_b = ev.bearing is not None and finite(yaw) and (heading or compass)
            if heading and has_b:
                ucols[i] = layout.u_columns(ev.observer)  # type: ignore[attr-defined]
                a = float(ev.bearing) + yaw  # type: ignore[arg-type]
                w = (math.cos(a), math.sin(a))
                if has_r:
                    rows.append(_Row("along", i, j, float(ev.range), ev.sigma_range**2, w=w))  # type: ignore[arg-type]
                rows.append(_Row("cross_unit", i, j, 0.0, ev.sigma_bearing**2, w=w, support=2.0))
                continue
            if has_r:
                rows.append(_Row("range", i, j, float(ev.range), ev.sigma_range**2))  # type: ignore[arg-type]
            if has_b:
                rows.append(
                    _Row(
                        "bearing",
                        i,
                        j,
                        float(ev.bearing),  # type: ignore[arg-type]
                        ev.sigma_bearing**2,
                        psi=yaw,
                        support=2.0 * math.pi,
                    )
                )
        if not rows:
            return []
        eps = OUTLIER_FRACTION if context.robust else 0.0
        return [cls(layout, tuple(rows), eps, ucols)]

    @classmethod
    def heard(cls, event: SightingEvent) -> tuple[str, ...]:
        return (event.observer, event.target)

    @classmethod
    def rejection(cls, event: SightingEvent, context: ValidationContext) -> str | None:
        """Unknown or identical robots, no value at all, non-finite or impossible values (a
        range not above zero, a bearing beyond +-pi, a noise not above zero): counted, never
        fused."""
        names = context.layout.robots
        if event.observer not in names or event.target not in names:
            return "unknown_robot"
        if event.observer == event.target:
            return "self_observation"
        if event.range is None and event.bearing is None:
            return "invalid_sighting"
        values = [v for v in (event.range, event.bearing) if v is not None]
        if not all(map(finite, (*values, event.sigma_range, event.sigma_bearing))):
            return "invalid_sighting"
        if event.sigma_range <= 0.0 or event.sigma_bearing <= 0.0:
            return "invalid_sighting"
        if event.range is not None and event.range <= 0.0:
            return "invalid_sighting"
        if event.bearing is not None and abs(event.bearing) > math.pi + 1e-9:
            return "bearing_out_of_range"
        if context.is_late(event.t):
            return "late_measurement"
        return None

    # ---------------------------------------------------------------- the rows
    def _relative(self, x: FloatArray, row: _Row) -> tuple[FloatArray, FloatArray]:
        """``v = p_target - p_observer`` of every state ``(M, D)`` (the reference at 0)."""
        n = x.shape[0]
        so, st = self.layout.slot_of(row.observer), self.layout.slot_of(row.target)
        po = x[:, 2 * so : 2 * so + 2] if so >= 0 else np.zeros((n, 2))
        pt = x[:, 2 * st : 2 * st + 2] if st >= 0 else np.zeros((n, 2))
        d = pt - po
        return d[:, 0], d[:, 1]

    def _evaluate(self, x: FloatArray, row: _Row) -> tuple[FloatArray, dict[int, FloatArray]]:
        """Residual ``z - h(x)`` (wrapped for a bearing) and ``dh/dx`` by state column."""
        vx, vy = self._relative(x, row)
        grad_v: tuple[FloatArray, FloatArray]
        grad_u: tuple[FloatArray, FloatArray] | None = None
        if row.kind == "range":
            dist = np.maximum(np.hypot(vx, vy), 1e-9)
            residual = row.z - dist
            grad_v = (vx / dist, vy / dist)
        elif row.kind == "bearing":
            r2 = np.maximum(vx * vx + vy * vy, 1e-18)
            residual = wrap(row.z - (np.arctan2(vy, vx) - row.psi))
            grad_v = (-vy / r2, vx / r2)
        else:
            c0, c1 = self.u_columns[row.observer]
            ux, uy = x[:, c0], x[:, c1]
            wx, wy = row.w
            dx, dy = wx * ux - wy * uy, wy * ux + wx * uy  # A(w) u
            if row.kind == "along":
                h = dx * vx + dy * vy
                grad_v = (dx, dy)
                ax, ay = vx, vy  # dh/dd
                # Where the observer's heading is known, the range itself: ``A(w) u . v`` is
                # ``|u| |v|``, so it would read the range as the odometry scale times the
                # distance and pull the scale towards 1 (module docstring).
                known = np.hypot(ux, uy) > 0.5
                if np.any(known):
                    dist = np.maximum(np.hypot(vx, vy), 1e-9)
                    h = np.where(known, dist, h)
                    grad_v = (np.where(known, vx / dist, dx), np.where(known, vy / dist, dy))
                    ax, ay = np.where(known, 0.0, ax), np.where(known, 0.0, ay)
            else:  # cross_unit: the sine of the bearing error, (A(w) u) x v / |v|
                norm = np.maximum(np.hypot(vx, vy), 1e-9)
                h = (dx * vy - dy * vx) / norm
                grad_v = (-dy / norm - h * vx / norm**2, dx / norm - h * vy / norm**2)
                ax, ay = vy / norm, -vx / norm
                # Where the observer's heading is known (|u| near its scale), the bearing
                # itself: the sine above cannot tell a teammate ahead from one behind.
                known = np.hypot(ux, uy) > 0.5
                if np.any(known):
                    d2 = np.maximum(dx * dx + dy * dy, 1e-18)
                    v2 = norm * norm
                    angle = wrap(np.arctan2(vy, vx) - np.arctan2(dy, dx))
                    h = np.where(known, angle, h)
                    grad_v = (
                        np.where(known, -vy / v2, grad_v[0]),
                        np.where(known, vx / v2, grad_v[1]),
                    )
                    # d angle(v) - angle(d) / dd = -(-dy, dx) / |d|^2
                    ax, ay = np.where(known, dy / d2, ax), np.where(known, -dx / d2, ay)
            # d = A(w) u: dd/du = A(w), so dh/du = A(w)^T dh/dd
            grad_u = (wx * ax + wy * ay, -wy * ax + wx * ay)
            residual = row.z - h
        grads: dict[int, FloatArray] = {}
        so, st = self.layout.slot_of(row.observer), self.layout.slot_of(row.target)
        if st >= 0:
            grads[2 * st], grads[2 * st + 1] = grad_v
        if so >= 0:
            grads[2 * so] = grads.get(2 * so, 0.0) - grad_v[0]
            grads[2 * so + 1] = grads.get(2 * so + 1, 0.0) - grad_v[1]
        if grad_u is not None:
            c0, c1 = self.u_columns[row.observer]
            grads[c0], grads[c1] = grad_u
        return residual, grads

    def log_likelihood(self, positions: FloatArray, particles: FloatArray) -> FloatArray:
        """Sum of the rows' robust densities at every particle ``(M,)``."""
        total = np.zeros(particles.shape[0])
        for row in self.items:
            residual, _ = self._evaluate(particles, row)
            ll, _ = robust_gaussian(
                residual, np.full_like(residual, row.variance), self.outlier_fraction, row.support
            )
            total += ll
        return total

    @property
    def rows(self) -> int:
        return len(self.items)

    def row(self, k: int, mean: FloatArray) -> LinearRow:
        """Row ``k`` linearised at every Gaussian's mean ``(M, D)``."""
        item = self.items[k]
        residual, grads = self._evaluate(mean, item)
        cols = np.array(sorted(grads), dtype=np.intp)
        jac = np.stack([np.broadcast_to(grads[c], residual.shape) for c in cols], axis=1)
        return LinearRow(cols, jac, residual, item.variance, self.outlier_fraction, item.support)

    def condition(self, positions: FloatArray, particles: FloatArray) -> None:
        """No sufficient statistics in the state."""
