"""The reorder buffer: events back in header-stamp order within a bounded window.

Reorder window
--------------
:class:`ReorderBuffer` restores header order within a bounded window: it holds events in a heap
and releases, in stamp order, those ``window`` seconds of header time behind the newest time the
source knows has arrived (live: the newest stamp; a bag: the newest receive time put on the
header clock, since a message received later is stamped earlier only by its lag), or that have
waited ``hold`` seconds (live, so that a quiet team is not held back). Memory stays bounded by a
window's worth of messages. An event older than one already released cannot be put in order
any more: it is counted (``late``) and either passed on at once (live: the localizer judges
whether it is too late) or dropped (a bag: an offline run sees strictly ordered events). The
window is latency: live, every event waits up to that long.
"""

from __future__ import annotations

import heapq
import math
from typing import Generic, TypeVar

__all__ = ["ReorderBuffer"]

T = TypeVar("T")


class ReorderBuffer(Generic[T]):
    """Releases items in header-stamp order after holding each for at most a window.

    The source :meth:`push`-es each item with its stamp (and receive time) and :meth:`advance`-s
    the buffer to the newest header time it knows has arrived. An item leaves once that time is
    ``window`` past its stamp, or once it has waited ``hold`` (receive-clock seconds), and in
    stamp order (ties in push order). One older than an item already released is *late*: it
    leaves at once, counted in :attr:`late`, and is returned, or dropped with ``drop_late``.
    ``window=0`` passes every item straight through.
    """

    def __init__(self, window: float, *, hold: float = math.inf, drop_late: bool = False) -> None:
        if window < 0:
            raise ValueError(f"reorder window must be >= 0, got {window}")
        self.window = float(window)
        self.hold = float(hold)
        self.drop_late = drop_late
        self._heap: list[tuple[float, int, float, T]] = []
        self._seq = 0
        self._newest = -math.inf
        self.last_released = -math.inf
        """Stamp of the newest item released so far."""
        self.late = 0
        """Items that came out after a later-stamped one (returned, or dropped)."""
        self.max_depth = 0
        """Most items held at once."""

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, t: float, item: T, received: float = 0.0) -> None:
        """Hold ``item`` stamped ``t``, received at ``received``."""
        heapq.heappush(self._heap, (t, self._seq, received, item))
        self._seq += 1
        if len(self._heap) > self.max_depth:
            self.max_depth = len(self._heap)

    def advance(self, t: float) -> None:
        """Header time ``t`` has been reached (the newest stamp, or receive time on the header
        clock)."""
        if t > self._newest:
            self._newest = t

    def pop_ready(self, now: float = -math.inf) -> list[T]:
        """Items due at receive time ``now``, in stamp order."""
        out: list[T] = []
        horizon = self._newest - self.window
        heap = self._heap
        while heap:
            t, _, received, _ = heap[0]
            late = t < self.last_released  # order is lost already: holding it cannot help
            if not late and t > horizon and now - received < self.hold:
                break
            self._release(heapq.heappop(heap), out)
        return out

    def flush(self) -> list[T]:
        """Everything held, in stamp order (end of a recording, shutdown)."""
        out: list[T] = []
        while self._heap:
            self._release(heapq.heappop(self._heap), out)
        return out

    def next_due(self) -> float | None:
        """Receive time at which the oldest held item is released by waiting, or ``None``."""
        return self._heap[0][2] + self.hold if self._heap else None

    def _release(self, entry: tuple[float, int, float, T], out: list[T]) -> None:
        t = entry[0]
        if t < self.last_released:
            self.late += 1
            if self.drop_late:
                return
        else:
            # Never past the buffer's own time: an item stamped ahead of it (a future stamp
            # let out by ``hold``) must not make every later item late.
            self.last_released = max(self.last_released, min(t, self._newest))
        out.append(entry[3])
