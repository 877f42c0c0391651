"""Glue: source -> stages -> localizer -> sinks. The same code runs offline and live.

A *pipeline* is one method: a chain of stages (range correction, detection association) in
front of one localizer. The engine hands every event of the source, in order, to every
pipeline, sets the ground truth aside (the localizers never see it: it goes to the *truth
sinks*, which evaluation supplies, e.g. ``relloc.evaluation.metrics.GroundTruth.add``), and passes
each estimate to the sinks and back to the pipeline's stages (association gates on it). The
engine knows no metric: evaluation sits above it.

Sources are iterables of events (simulator, rosbag2 file) or callbacks (Zenoh): ``Engine.feed``
takes one event, ``Engine.run`` a whole iterable.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Protocol

from relloc.estimate import Estimate
from relloc.events import Event, GroundTruthEvent
from relloc.localizers.base import Localizer


class Stage(Protocol):
    """Transforms events between source and localizer (e.g. corrects ranges)."""

    @property
    def stats(self) -> Mapping[str, int]:
        """What the stage counted (rejections, corrections), by name."""
        ...

    def process(self, event: Event) -> list[Event]: ...

    def feedback(self, estimate: Estimate) -> None: ...


Sink = Callable[[Estimate], None]
TruthSink = Callable[[GroundTruthEvent], None]


@dataclass
class Pipeline:
    """One method: stages in front of a localizer, and the estimates it produced."""

    name: str
    localizer: Localizer
    stages: list[Stage] = field(default_factory=list)
    estimates: list[Estimate] = field(default_factory=list)
    compute_s: float = 0.0

    def feed(self, event: Event) -> list[Estimate]:
        events = [event]
        for stage in self.stages:
            events = [out for ev in events for out in stage.process(ev)]
        out: list[Estimate] = []
        for ev in events:
            out += self.localizer.process(ev)
        return out

    def finish(self) -> list[Estimate]:
        return self.localizer.flush()

    def stats(self) -> dict[str, int]:
        merged: dict[str, int] = dict(self.localizer.stats)
        for stage in self.stages:
            for k, v in stage.stats.items():
                merged[f"{type(stage).__name__}.{k}"] = v
        return merged


class Engine:
    """Feeds events to pipelines, collects estimates, calls sinks; ground truth to truth sinks."""

    def __init__(
        self,
        pipelines: list[Pipeline],
        sinks: list[Sink] | None = None,
        *,
        truth_sinks: list[TruthSink] | None = None,
        keep_estimates: int | None = None,
    ) -> None:
        """``truth_sinks`` receive every ground-truth event (none: it is dropped, as live).
        ``keep_estimates`` bounds how many estimates each pipeline keeps (a live server runs for
        hours; offline evaluation keeps all, ``None``)."""
        self.pipelines = pipelines
        self.sinks = sinks or []
        self.truth_sinks = truth_sinks or []
        self.keep_estimates = keep_estimates
        self.events = 0
        self.t_first: float | None = None
        self.t_last: float | None = None

    def feed(self, event: Event) -> list[Estimate]:
        self.events += 1
        if self.t_first is None:
            self.t_first = event.t
        self.t_last = event.t
        if isinstance(event, GroundTruthEvent):
            for truth_sink in self.truth_sinks:
                truth_sink(event)
            return []
        produced: list[Estimate] = []
        for p in self.pipelines:
            start = time.perf_counter()
            new = p.feed(event)
            p.compute_s += time.perf_counter() - start
            self._emit(p, new)
            produced += new
        return produced

    def finish(self) -> None:
        for p in self.pipelines:
            self._emit(p, p.finish())

    def run(
        self, events: Iterable[Event], progress: Callable[[float], None] | None = None
    ) -> Engine:
        """Feed a whole source; ``progress`` is called with each event's time."""
        for ev in events:
            self.feed(ev)
            if progress is not None:
                progress(ev.t)
        self.finish()
        return self

    def _emit(self, pipeline: Pipeline, estimates: list[Estimate]) -> None:
        for est in estimates:
            pipeline.estimates.append(est)
            if self.keep_estimates is not None and len(pipeline.estimates) > self.keep_estimates:
                del pipeline.estimates[: len(pipeline.estimates) - self.keep_estimates]
            for stage in pipeline.stages:
                stage.feedback(est)
            for sink in self.sinks:
                sink(est)
