"""What every recorded or simulated event source offers: the :class:`Source` protocol.

A source is a finite stream of one team's time-ordered events that can be iterated again from
the start, with what a run needs to know before and after it: its name, its time span, the
team config its events belong to, non-fatal problems found when opening it, and counters of
what it read and dropped. Where a data set knows every robot's true starting pose (MRCLAM's
Vicon, a simulation), :meth:`Source.initial_poses` gives it, for oracle baselines only; the
others return ``None``. The live Zenoh source is push-based (it has no end and no time span)
and does not follow this protocol; it shares the counters (:class:`SourceStats`).

The sources are classes of their own modules that follow the protocol structurally; which one
a path names is :mod:`relloc.sources.table`'s business.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any, Protocol

from relloc.config import TeamConfig
from relloc.events import Event

Pose = tuple[float, float, float]
"""``(x, y, yaw)`` in the world frame (m, rad)."""


class SourceStats(Protocol):
    """What a source read and left out."""

    @property
    def rejected(self) -> Mapping[str, int]:
        """Dropped messages or values by reason."""
        ...

    def as_dict(self) -> dict[str, Any]:
        """Plain-dict view for ``--json`` output."""
        ...


class Source(Protocol):
    """A finite, time-ordered event stream of one team; each iteration starts afresh and
    resets :attr:`stats`."""

    @property
    def name(self) -> str:
        """The recording's (or scenario's) name: the run's label and output folder."""
        ...

    @property
    def config(self) -> TeamConfig:
        """The team the events belong to."""
        ...

    @property
    def warnings(self) -> list[str]:
        """Non-fatal problems found when opening it, one line each."""
        ...

    @property
    def stats(self) -> SourceStats:
        """Counters of the last iteration."""
        ...

    @property
    def start_time(self) -> float:
        """Time of the first event (s, on the events' clock)."""
        ...

    @property
    def duration(self) -> float:
        """Length of the stream (s)."""
        ...

    def __iter__(self) -> Iterator[Event]: ...

    def initial_poses(self) -> dict[str, Pose] | None:
        """Every robot's true pose at the start, where the data set knows it (oracle
        baselines only: never given to relloc's filters); ``None`` otherwise."""
        ...
