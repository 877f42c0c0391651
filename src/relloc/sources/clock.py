"""The header clock: receive times put on the clock of the header stamps.

Header stamps and receive time
------------------------------
Events carry **header stamps**: the time the sensor captured the data, on one clock for the
whole team. The time a message *arrived* is later, by a lag that depends on the kind of
message (detections wait for the image pipeline, odometry for its own loop), so messages of
different topics arrive out of header order. Receive time is used only where no stamp exists.

:class:`HeaderClock` puts a receive time on the header clock: ``header = offset(kind) + rate *
receive``, where the offset of a kind of message is the median, over the topics of that kind,
of each topic's median of ``stamp - rate * receive`` (kinds are kept apart so that a restamped
odometry message keeps odometry's lag; a kind never seen stamped uses the median over all
topics; with nothing seen at all the offset is 0, which is right live: ROS stamps wall time).
``rate`` is header seconds per receive second (a recording replayed twice as fast: 2).

The two clocks need not be close. A recording that was re-recorded from a replay has receive
times from the day of the replay and header stamps from the day of the experiment (weeks
apart, on one of the shared recordings), but the offset between them is constant over
the recording. A bag source can therefore estimate it once, from the header stamps at the start
of the bag, and :meth:`HeaderClock.freeze` it; a live source cannot look ahead and learns it as
messages come (a running median over each topic's last ``window`` stamped messages).
``TeamConfig.clock_offset`` fixes the offset instead of estimating it.
"""

from __future__ import annotations

import statistics
from collections import Counter, deque

__all__ = ["HeaderClock"]


class HeaderClock:
    """Puts receive times on the header clock: ``header = offset(kind) + rate * receive``.

    :meth:`observe` learns from the header stamps of one *stream* (a topic or a key) of a kind;
    zero stamps are counted, not learned from. Each stream keeps its last ``window`` offsets
    ``stamp - rate * receive``; the offset of a kind is the median of its streams' medians (a
    kind never seen stamped: the median over all streams; nothing seen: 0).
    ``fixed_offset`` overrides every estimate. After :meth:`freeze` observations are ignored and
    the offsets stay as they are (a recording's clock offset is constant).
    """

    def __init__(
        self, rate: float = 1.0, fixed_offset: float | None = None, window: int = 200
    ) -> None:
        if not rate > 0:
            raise ValueError(f"clock rate must be positive, got {rate}")
        self.rate = float(rate)
        self.fixed_offset = fixed_offset
        self.frozen = False
        self._window = window
        self._samples: dict[str, deque[float]] = {}
        self._of_kind: dict[str, list[str]] = {}
        self._zeros: Counter[str] = Counter()
        self._medians: dict[str, float] = {}
        self._stale: set[str] = set()

    def observe(self, stream: str, kind: str, stamp: float, received: float) -> None:
        """Learn from a message of ``stream`` (of ``kind``) stamped ``stamp``, received then."""
        if self.frozen:
            return
        if stamp == 0.0:
            self._zeros[stream] += 1
            return
        samples = self._samples.get(stream)
        if samples is None:
            samples = self._samples[stream] = deque(maxlen=self._window)
            self._of_kind.setdefault(kind, []).append(stream)
        samples.append(stamp - self.rate * received)
        self._stale.add(stream)

    def freeze(self) -> None:
        """Stop learning: the offsets stay those estimated so far."""
        self.frozen = True

    def seen(self, stream: str) -> int:
        """Messages of ``stream`` observed and kept (stamped or zero)."""
        samples = self._samples.get(stream)
        return (len(samples) if samples else 0) + self._zeros[stream]

    @property
    def zero_stamp_streams(self) -> set[str]:
        """Streams observed with zero stamps only."""
        return {s for s, n in self._zeros.items() if n and s not in self._samples}

    @property
    def zeros_seen(self) -> bool:
        """Whether any zero stamp was observed."""
        return bool(self._zeros)

    def stream_offsets(self) -> dict[str, float]:
        """Median ``stamp - rate * receive`` per stream, in the order the streams were first
        observed stamped."""
        return {s: self._median(s) for s in self._samples}

    def offset(self, kind: str) -> float:
        """Current estimate of ``header - rate * receive`` for messages of ``kind``."""
        if self.fixed_offset is not None:
            return self.fixed_offset
        own = self._of_kind.get(kind)
        if own:
            return statistics.median([self._median(s) for s in own])
        return self.overall

    @property
    def overall(self) -> float:
        """Offset over all streams (the fixed one, if set; 0 with nothing seen)."""
        if self.fixed_offset is not None:
            return self.fixed_offset
        medians = self.stream_offsets()
        return statistics.median(medians.values()) if medians else 0.0

    def stamp(self, kind: str, received: float) -> float:
        """Header-clock time of a message of ``kind`` received at ``received``."""
        return self.offset(kind) + self.rate * received

    def _median(self, stream: str) -> float:
        """The stream's median offset, recomputed only after new observations."""
        if stream in self._stale:
            self._medians[stream] = statistics.median(self._samples[stream])
            self._stale.discard(stream)
        return self._medians[stream]
