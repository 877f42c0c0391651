"""A part of a source: its events between two times counted from its start.

What a user does to calibrate on one half of a recording and score on the other
(``relloc calibrate --span 0:17``, ``relloc run --span 17:``): the same bag, two disjoint
windows, so that nothing fitted on one is judged on itself. Times are seconds from the
source's :attr:`~relloc.sources.protocol.Source.start_time` (the header clock).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

from relloc.config import TeamConfig
from relloc.events import Event
from relloc.sources.protocol import Pose, Source, SourceStats

__all__ = ["Span", "SpanSource", "parse_span"]

Span = tuple[float, float]
"""``(start, end)`` in seconds from the source's start; ``end`` may be ``inf``."""
LATE = 10.0
"""How far past the span's end (s) events are still read: a recording is ordered by receive
time, so an event stamped inside the span may follow one stamped after it."""


def parse_span(text: str) -> Span:
    """``"A:B"``, ``"A:"`` or ``":B"`` (seconds) as a span; a :class:`ValueError` that says
    what is wrong otherwise."""
    head, sep, tail = text.partition(":")
    if not sep:
        raise ValueError(f"expected START:END in seconds (either may be left out), got {text!r}")
    try:
        start = float(head) if head.strip() else 0.0
        end = float(tail) if tail.strip() else math.inf
    except ValueError:
        raise ValueError(f"expected numbers in START:END, got {text!r}") from None
    if not (math.isfinite(start) and start >= 0.0 and end > start):
        raise ValueError(f"expected 0 <= START < END, got {text!r}")
    return start, end


class SpanSource:
    """The events of ``source`` with ``start <= t - source.start_time < end``."""

    def __init__(self, source: Source, span: Span) -> None:
        self.source = source
        self.span = span
        if span[0] >= source.duration:
            raise ValueError(
                f"span starts at {span[0]:g} s, after the end of {source.name} ({source.duration:.1f} s)"
            )

    @property
    def name(self) -> str:
        return self.source.name

    @property
    def config(self) -> TeamConfig:
        return self.source.config

    @property
    def warnings(self) -> list[str]:
        return self.source.warnings

    @property
    def stats(self) -> SourceStats:
        return self.source.stats

    @property
    def start_time(self) -> float:
        return self.source.start_time + self.span[0]

    @property
    def duration(self) -> float:
        return min(self.span[1], self.source.duration) - self.span[0]

    def __iter__(self) -> Iterator[Event]:
        lo = self.start_time
        hi = self.source.start_time + self.span[1]
        for event in self.source:
            if event.t >= hi + LATE:
                return
            if lo <= event.t < hi:
                yield event

    def initial_poses(self) -> dict[str, Pose] | None:
        """None unless the span starts with the source: the poses are the source's start's."""
        return self.source.initial_poses() if self.span[0] == 0.0 else None
