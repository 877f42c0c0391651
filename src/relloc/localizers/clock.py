"""The team clock: a time that no single stamp can capture.

The first events wait until ``_WARMUP_EVENTS`` of them, from two streams (robots' odometry,
range pairs, ...: :func:`stream`), are in, or twice as many from one, and their median stamp
sets the clock. After that a stamp more than ``MAX_TIME_JUMP`` ahead of the clock (the newest
accepted stamp), or behind it where the event could no longer be used, is rejected
(``time_jump``, ``time_jump_backward``) and votes for a jump to its time. The clock follows
once ``_JUMP_VOTES`` agreeing votes came from at least two streams (one if the team has only
one), each event accepted meanwhile taking one vote away: one robot's wrong clock, or stray
stamps minutes apart, never move it; a step of the whole stream does, either way.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from relloc.events import Event, OdometryEvent
from relloc.filter.measurement import hook
from relloc.filter.registry import model_for

_JUMP_VOTES = 3
"""Agreeing votes (from two streams at least) before the clock follows a jump."""
MAX_TIME_JUMP = 5.0
"""The clock's tolerance (s): farther than this from the clock, a stamp is rejected and votes
for a jump (module docstring); minutes of real gaps pass, one corrupted stamp does not."""
_WARMUP_EVENTS = 5
"""Events (from two streams, or twice as many from one) whose median stamp sets the clock."""


def stream(event: Event) -> tuple[str, ...]:
    """Which stream ``event`` belongs to: its robot's odometry (the motion input, no model's
    event), else what its measurement model says (``MeasurementModel.stream``)."""
    if isinstance(event, OdometryEvent):
        return (type(event).__name__, str(event.robot))
    model = model_for(event)
    assert model is not None, "only odometry and measurement events reach the clock"
    stream: tuple[str, ...] = hook(model, "stream")(event)
    return stream


class TeamClock:
    """The warm-up, the check of every later stamp, and the jump votes (module docstring)."""

    def __init__(self, max_time_jump: float = MAX_TIME_JUMP) -> None:
        self.limit = max_time_jump
        self.now = -math.inf
        """The newest accepted stamp (``-inf``: not set yet, the warm-up)."""
        self._warmup: list[Event] = []
        self._streams: set[tuple[str, ...]] = set()  # streams whose events were accepted
        self._candidate = math.nan  # stamp of the last vote for a jump
        self._ahead = True  # whether that vote is for a jump forward
        self._votes = 0  # agreeing votes, less the events accepted since
        self._vote_streams: set[tuple[str, ...]] = set()

    @property
    def started(self) -> bool:
        """Whether the warm-up is over (the clock is set)."""
        return self.now != -math.inf

    def warm(self, event: Event) -> list[Event]:
        """Hold one of the first events; once they are enough (module docstring), set the
        clock at their median stamp and return them all, in arrival order, each still to be
        checked (an outlier among them is rejected). Empty while the warm-up lasts."""
        self._warmup.append(event)
        n = len(self._warmup)
        if n >= _WARMUP_EVENTS and (
            len({stream(e) for e in self._warmup}) >= 2 or n >= 2 * _WARMUP_EVENTS
        ):
            return self.end_warmup()
        return []

    def end_warmup(self) -> list[Event]:
        """Set the clock at the median stamp of the events held (if any) and return them."""
        events, self._warmup = self._warmup, []
        if events:
            self.now = float(np.median([e.t for e in events]))
        return events

    def check(self, event: Event, unusable: Callable[[Event], bool]) -> str | None:
        """``None`` to accept ``event``'s stamp, ``"follow"`` when it completes the vote for a
        jump of the whole stream, else the rejection reason. ``unusable``: whether an event
        behind the window could no longer be used anyway (else it is a late stream, not a
        clock step: the event's own checks apply)."""
        t, limit = event.t, self.limit
        ahead = t > self.now + limit
        if not ahead and t >= self.now - limit:
            return None
        if not ahead and not unusable(event):
            return None
        if self._votes and abs(t - self._candidate) <= limit and ahead == self._ahead:
            self._votes += 1
        else:
            self._votes, self._vote_streams = 1, set()
            self._ahead = ahead
        self._candidate = t
        self._vote_streams.add(stream(event))
        if self._votes >= _JUMP_VOTES and len(self._vote_streams) >= min(
            2, max(len(self._streams), 1)
        ):
            return "follow"
        return "time_jump" if ahead else "time_jump_backward"

    def accepted(self, event: Event) -> None:
        """An event passed the check: it wears a jump candidate down, and its stream counts."""
        if self._votes:
            self._votes -= 1
            if not self._votes:
                self._vote_streams.clear()
        self._streams.add(stream(event))

    def advance(self, t: float) -> None:
        self.now = max(self.now, t)

    def follow(self, dt: float) -> None:
        """The whole stream stepped by ``dt``: the votes are spent, the clock moves."""
        self._votes, self._vote_streams, self._candidate = 0, set(), math.nan
        self.now += dt
