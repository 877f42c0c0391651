"""The batching grid, and the live wake rule it implies.

Measurements stamped within one cell of a fixed ``UPDATE_PERIOD`` grid are fused as one batch
(the stacked measurement vector of the paper), at the batch's newest stamp. A grid, not a
window opened by the first measurement: a pair ranging at the update rate with some jitter
then gives one range per batch, not now one, now two. A batch closes when a measurement of a
later cell arrives, when odometry reaches two cells past the batch's (every robot's motion up
to the batch time is then known), or when it holds ``_MAX_PENDING`` measurements (counted
``batches_forced``): a batch never grows.

The same object says which events could close a batch now (:meth:`BatchGrid.wake_rule`): a
live server processes those at once and lets the others wait. Both read the same state and
the same bounds, so the rule cannot drift from the batching.
"""

from __future__ import annotations

import math
from typing import Any

from relloc.events import WAKE_ALWAYS, WakeRule

UPDATE_PERIOD = 0.1
"""The grid's cell (s): measurements within one are fused in one update, a tenth of a second
like the sensors' fastest rates."""
_MAX_PENDING = 5000
"""A batch this large is fused at once (counted ``batches_forced``): a batch never grows."""
_WAKE_MARGIN = 1e-5
"""Seconds by which a :class:`WakeRule`'s bounds are moved towards waking: more than the
rounding of ``floor(t / period)`` at epoch stamps (about 4e-7 s)."""


class BatchGrid:
    """The pending batch on the ``update_period`` grid (module docstring)."""

    def __init__(self, update_period: float = UPDATE_PERIOD) -> None:
        self.period = update_period
        self.pending: list[Any] = []
        self.start = math.nan
        """Stamp of the pending batch's first measurement (its cell is the batch's)."""
        self.closed_until = -math.inf
        """The newest fused batch time: a measurement older than this comes too late."""

    def cell(self, t: float) -> int:
        """Index of the grid cell that holds time ``t``."""
        return math.floor(t / self.period)

    @property
    def full(self) -> bool:
        return len(self.pending) >= _MAX_PENDING

    def closed_by(self, t: float) -> bool:
        """Whether a measurement stamped ``t`` closes the pending batch before joining one: it
        falls in a later cell, or the batch is full."""
        return bool(self.pending) and (self.cell(t) > self.cell(self.start) or self.full)

    def add(self, measurement: Any) -> None:
        if not self.pending:
            self.start = measurement.t
        self.pending.append(measurement)

    def due(self, now: float) -> bool:
        """Whether odometry that reached ``now`` closes the pending batch."""
        return bool(self.pending) and now >= self._odometry_from()

    def _odometry_from(self) -> float:
        """From when odometry closes the pending batch: two cells past its own."""
        return (self.cell(self.start) + 2) * self.period

    def take(self) -> tuple[float, list[Any]]:
        """The pending batch and its time (its newest stamp), which the filter moves to."""
        batch, self.pending = self.pending, []
        t = max(m.t for m in batch)
        self.closed_until = max(self.closed_until, t)
        return t, batch

    def is_late(self, t: float) -> bool:
        return t < self.closed_until

    def wake_rule(self, clock: float, limit: float) -> WakeRule:
        """Which events could close a batch now, given the team ``clock`` (``-inf`` in the
        warm-up) and its ``max_time_jump`` ``limit``: any other event can wait and be
        processed later, in its order, with the same result (:class:`WakeRule`).

        A measurement is urgent from the cell after the pending batch's (where
        :meth:`closed_by` turns true), or always when no batch is pending (it opens one: once
        processed, the rule knows its cell) or the batch nears ``_MAX_PENDING``; odometry from
        :meth:`due`'s bound (never with no batch pending). Every event is urgent during the
        warm-up and outside the ``limit`` window about the clock (a vote for a jump). The
        bounds are moved by ``_WAKE_MARGIN`` towards urgent, so rounding can only wake too
        often."""
        if clock == -math.inf:
            return WAKE_ALWAYS
        lo, hi = clock - limit + _WAKE_MARGIN, clock + limit - _WAKE_MARGIN
        if not self.pending:
            return WakeRule(-math.inf, math.inf, lo, hi)
        if len(self.pending) >= _MAX_PENDING // 2:
            return WakeRule(-math.inf, -math.inf, lo, hi)
        measurement_from = (self.cell(self.start) + 1) * self.period
        return WakeRule(
            measurement_from - _WAKE_MARGIN, self._odometry_from() - _WAKE_MARGIN, lo, hi
        )
