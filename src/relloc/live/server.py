"""``LiveServer``: the engine fed by a Zenoh source, publishing through a Zenoh sink.

It runs the *same* :class:`~relloc.engine.Engine` and method pipelines as ``relloc run`` and
the demo. Zenoh's callbacks only enqueue (:class:`~relloc.sources.zenoh_source.ZenohSource`);
one thread, the caller of :meth:`LiveServer.run`, decodes, feeds the engine and publishes
(:class:`~relloc.sinks.zenoh_sink.ZenohSink`), so filter state is never shared between threads.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from relloc.config import TeamConfig
from relloc.engine import Engine, Pipeline
from relloc.estimate import Estimate
from relloc.events import RangeEvent, WakeRule
from relloc.faults import FaultInjector, Faults
from relloc.filter import compiled
from relloc.methods import DETECTION_METHODS
from relloc.ros.interfaces import RosInterface
from relloc.sinks.mcap import McapWriter
from relloc.sinks.zenoh_sink import ZenohSink
from relloc.sources.zenoh_source import Arrival, ZenohSource, ZenohSourceOptions

if TYPE_CHECKING:
    from relloc.sinks.foxglove import FoxgloveSink

__all__ = ["LiveServer", "ServeOptions"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ServeOptions:
    """What ``relloc serve`` runs and how it talks."""

    methods: tuple[str, ...] = ("pf",)
    seed: int = 0
    particles: int | None = None
    models: Path | None = None
    prefix: str = ""
    """Key prefix of the robots' topics (the bridge's namespace)."""
    interface: RosInterface = field(default_factory=RosInterface)
    """How the robots' topics and relloc's own are on Zenoh: ``bridge`` or ``rmw_zenoh``."""
    out_prefix: str = "relloc"
    """Key prefix of what the server publishes."""
    faults: Faults = field(default_factory=Faults)
    """Faults injected into the received events (testing; :mod:`relloc.faults`)."""
    reorder_window: float = 0.0
    """Reorder-buffer window (s of header time); 0: lowest latency (see ``docs/explanation/live-engine.md``)."""
    clock_rate: float = 1.0
    """Header seconds per wall second: pair with ``relloc replay --rate``."""
    reorder_hold: float | None = None
    """Wall seconds an event waits in the reorder buffer at most (``None``: the window on the
    wall clock; ``math.inf``: released by the stamps alone, a replay compared to a run)."""
    status_period: float = 1.0
    trace: bool = False
    subscribe_all: bool = False
    quiet_after: float = 2.0
    """A robot silent this long (s) is reported as quiet in the status."""
    keep_estimates: int = 2000
    """Estimates kept per pipeline in memory (the engine keeps all; a server runs for hours)."""
    record: Path | None = None
    """An MCAP file of every estimate published, its flags and the ranges fed to the methods
    (:class:`~relloc.sinks.mcap.McapWriter`), finished by :meth:`LiveServer.close`."""
    robot: str = ""
    """On board: the robot this server runs on (``relloc serve --robot``). It is the
    reference, its teammates are published in its body frame below ``<out_prefix>/<robot>``
    (:meth:`LiveServer.onboard`); empty: one central view from the config's reference."""
    foxglove: str | None = None
    """``[HOST:]PORT`` of a Foxglove WebSocket server showing the team
    (:class:`~relloc.sinks.foxglove.FoxgloveSink`, the ``viewer`` extra); ``None``: none."""
    foxglove_rate: float = 10.0
    """At most this many messages a second on each Foxglove channel."""
    ground_truth: bool = False
    """Subscribe to the robots' motion capture for the viewer's truth and error (its truth
    sink; never the localizers'); off: not received at all."""
    compiled: bool | None = None
    """Whether the particle filter's step runs compiled (numba) during :meth:`LiveServer.run`;
    ``None``: :func:`relloc.filter.compiled.serve_default` (NumPy unless ``RELLOC_COMPILED=1``).
    NumPy keeps numba unimported (a serve under 100 MB resident) at some more CPU."""


class LiveServer:
    """The engine, fed by a Zenoh source, publishing through a Zenoh sink.

    ``start`` declares the subscribers; ``run`` is the engine loop (on the calling thread) until
    :meth:`stop` or ``duration``; ``close`` undeclares everything. The session belongs to the
    caller. Any exception of the engine on one event is logged and counted
    (``engine_errors``), never allowed to stop the server.
    """

    def __init__(
        self, config: TeamConfig, session: Any, options: ServeOptions | None = None
    ) -> None:
        from relloc.methods import build_pipeline

        self.options = opts = options or ServeOptions()
        if not opts.methods:
            raise ValueError("serve needs at least one method")
        if opts.particles:
            config = config.with_filter(particles=opts.particles)
        if opts.robot:
            if opts.robot not in config.robot_names:
                raise ValueError(
                    f"--robot {opts.robot!r} is not one of the team: {list(config.robot_names)}"
                )
            config = config.with_modes(reference=opts.robot)
        self.config = config
        out_prefix = "/".join(p for p in (opts.out_prefix.strip("/"), opts.robot) if p)
        self.session = session
        self.pipelines: list[Pipeline] = [
            build_pipeline(m, config, seed=opts.seed, models=opts.models) for m in opts.methods
        ]
        for p in self.pipelines:  # nothing smooths a served run afterwards: bounded memory
            p.localizer.keeps_run = False
        self.source = ZenohSource(
            config,
            ZenohSourceOptions(
                prefix=opts.prefix,
                interface=opts.interface,
                reorder_window=opts.reorder_window,
                clock_rate=opts.clock_rate,
                reorder_hold=opts.reorder_hold,
                detections=any(m in DETECTION_METHODS for m in opts.methods),
                ground_truth=opts.ground_truth,
                subscribe_all=opts.subscribe_all,
                own_prefix=out_prefix,
            ),
        )
        self.sink = ZenohSink(
            session,
            config,
            interface=opts.interface,
            prefix=out_prefix,
            primary_method=opts.methods[0],
            trace=opts.trace,
        )
        self.engine = Engine(
            self.pipelines,
            [self.onboard if opts.robot else self.sink],
            keep_estimates=opts.keep_estimates,
        )
        self.faults = FaultInjector(opts.faults) if opts.faults.active else None
        """What the server injects into its events (``None``: nothing)."""
        self.wake_by_rule = (
            opts.reorder_window == 0.0
            and self.faults is None
            and not any(p.stages for p in self.pipelines)
        )
        """Whether the engine thread is woken only for the messages that could make an
        estimate (:meth:`ZenohSource.rearm <relloc.sources.zenoh_source.ZenohSource.rearm>`):
        where the localizers see the messages' events unchanged and in arrival order (no
        reorder window, no stage, no injected fault); else for every message."""
        self.engine_errors = 0
        self.engine_thread_cpu_s = 0.0
        """CPU time of the thread that ran :meth:`run` (the rest is Zenoh's threads)."""
        self.started = time.time()
        self._stopping = False
        self._quiet: set[str] = set()
        self._last_counts: tuple[float, dict[str, int]] = (self.started, {})
        self.viewer: FoxgloveSink | None = None
        """The Foxglove server (``foxglove``), fed what the Zenoh sink is, ranges and truth."""
        if opts.foxglove is not None:
            from relloc.sinks.foxglove import FoxgloveSink

            first = self.pipelines[0].localizer
            self.viewer = FoxgloveSink(
                config, opts.foxglove, prefix=out_prefix, method=opts.methods[0],
                rate=opts.foxglove_rate, rejections=lambda: sum(first.rejected.values()),
                truth=opts.ground_truth,
            )  # fmt: skip
            if not opts.robot:
                self.engine.sinks.append(self.viewer)
            self.engine.truth_sinks.append(self.viewer.truth)
        self.recorder: McapWriter | None = None
        """The ``record`` file being written (opened last: nothing after it can fail)."""
        if opts.record is not None:
            try:
                self.recorder = McapWriter(opts.record, distro=opts.interface.distro)
            except Exception:
                if self.viewer is not None:
                    self.viewer.close()
                raise
            self.engine.sinks.append(self.recorder.estimate)

    def onboard(self, estimate: Estimate) -> None:
        """The onboard sink: ``estimate`` in the robot's body frame (its odometry heading in
        the team's heading frame turns a compass team's estimate,
        :meth:`Estimate.in_body_frame`), then published."""
        pipeline = next((p for p in self.pipelines if p.name == estimate.method), None)
        if pipeline is not None:
            yaw = pipeline.localizer.odometry.pose(self.config.reference, estimate.t)[2]
            estimate = estimate.in_body_frame(yaw)
        self.sink(estimate)
        if self.viewer is not None:
            self.viewer(estimate)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Subscribe to the team's keys."""
        self.source.attach(self.session, self.sink.node)
        self._ask_consumers()
        self.started = time.time()
        self._last_counts = (self.started, self._counts())

    def stop(self) -> None:
        """Ask :meth:`run` to finish (safe from any thread and from a signal handler)."""
        self._stopping = True  # a plain store: no lock a signal handler could deadlock on
        self.source.wake()  # SimpleQueue.put is reentrant: fine in a signal handler

    def close(self) -> None:
        """Undeclare subscribers and publishers (the session stays open); finish the record."""
        try:
            self.source.detach()
            self.sink.close()
        finally:
            if self.viewer is not None:
                self.viewer.close()
            if self.recorder is not None:
                self.recorder.close()

    def run(self, duration: float | None = None) -> dict[str, Any]:
        """Process messages until :meth:`stop` or ``duration`` seconds; returns :meth:`summary`.

        At the end, what is queued or held is processed, the pending batch is fused (one last
        estimate) and a final status is published. The filter step is the one
        :attr:`ServeOptions.compiled` chooses, for this run only.
        """
        choice = self.options.compiled
        with compiled.chosen(compiled.serve_default() if choice is None else choice):
            return self._run(duration)

    def _run(self, duration: float | None) -> dict[str, Any]:
        cpu_start = time.thread_time()
        now = time.time()
        deadline = math.inf if duration is None else now + duration
        period = self.options.status_period
        next_status = now + period
        while not self._stopping:
            now = time.time()
            if now >= deadline:
                break
            timeout = max(0.0, min(0.2, next_status - now, deadline - now))
            arrivals = self.source.poll(timeout)
            self._ask_consumers()
            self.feed(arrivals)
            now = time.time()
            if now >= next_status:
                self.feed(self.source.take_queued())  # the status counts every message received
                self._publish_status(now)
                next_status = max(next_status + period, now + 0.5 * period)
            if self.wake_by_rule:
                self.source.rearm(self._wake_rule())
        self.feed(self.source.drain())
        try:
            self.engine.finish()
        except Exception:
            self.engine_errors += 1
            log.exception("the engine failed while finishing")
        self._publish_status(time.time())
        self.engine_thread_cpu_s += time.thread_time() - cpu_start
        return self.summary()

    def _ask_consumers(self) -> None:
        """Each localizer computes the shape and distances only while someone subscribes to
        its method's shape key (they are published nowhere else)."""
        for p in self.pipelines:
            p.localizer.shape_wanted = self.sink.shape_wanted(p.name)

    def _wake_rule(self) -> WakeRule:
        """Which messages could make an estimate now: urgent for any method's localizer."""
        if len(self.pipelines) == 1:
            return self.pipelines[0].localizer.wake_rule()
        return WakeRule.combine(p.localizer.wake_rule() for p in self.pipelines)

    def feed(self, arrivals: Iterable[Arrival]) -> None:
        """Run the engine on released events (what :meth:`run` does with each poll)."""
        for arrival in arrivals:
            event = self.faults(arrival.event) if self.faults is not None else arrival.event
            if event is None:
                continue
            self.sink.set_trigger(arrival)
            try:
                if isinstance(event, RangeEvent):
                    if self.recorder is not None:
                        self.recorder.range(event)
                    if self.viewer is not None:
                        self.viewer.range(event)
                self.engine.feed(event)
            except Exception:
                self.engine_errors += 1
                log.exception("the engine failed on %r; skipped", arrival.event)
        self.sink.set_trigger(None)

    # ------------------------------------------------------------------ status
    def _counts(self) -> dict[str, int]:
        st = self.source.stats
        counts = {"messages": sum(st.messages.values())}
        counts.update({f"event.{k}": v for k, v in st.events.items()})
        counts.update({f"estimate.{p.name}": self.sink.published[p.name] for p in self.pipelines})
        return counts

    def _publish_status(self, now: float) -> None:
        status = self.status(now)
        try:
            self.sink.publish_status(status)
            if self.viewer is not None:
                self.viewer.publish_status(status)
        except Exception as exc:  # a closed session at shutdown: the status is not vital
            log.warning("could not publish the status: %s", exc)

    def status(self, now: float | None = None) -> dict[str, Any]:
        """The status published on ``<prefix>/status`` (rates since the previous call)."""
        now = time.time() if now is None else now
        then, before = self._last_counts
        counts = self._counts()
        dt = max(now - then, 1e-9)
        self._last_counts = (now, counts)

        def rate(name: str) -> float:
            return round((counts.get(name, 0) - before.get(name, 0)) / dt, 2)

        st = self.source.stats
        robots: dict[str, Any] = {}
        for r in self.config.robot_names:
            last = st.last_received.get(r)
            age = None if last is None else round(now - last, 3)
            quiet = age is None or age > self.options.quiet_after
            if quiet and last is not None and r not in self._quiet:
                log.warning("%s has been quiet for %.1f s", r, age)
            if not quiet and r in self._quiet:
                log.warning("%s publishes again", r)
            if quiet and last is not None:
                self._quiet.add(r)
            else:
                self._quiet.discard(r)
            robots[r] = {"last_message_age_s": age, "quiet": quiet}
        methods: dict[str, Any] = {}
        for p in self.pipelines:
            last_est = self.sink.last.get(p.name)
            methods[p.name] = {
                "estimates": self.sink.published[p.name],
                "rate_hz": rate(f"estimate.{p.name}"),
                "last_estimate_t": None if last_est is None else last_est.t,
                "ess": None if last_est is None or last_est.ess is None else round(last_est.ess, 1),
                "frame": None if last_est is None else last_est.frame,
                "orientation_observable": None
                if last_est is None
                else last_est.orientation_observable,
                "mode_weight": None if last_est is None else round(last_est.mode_weight, 3),
                "n_modes": None if last_est is None else last_est.n_modes,
                "particles": None if last_est is None else last_est.particles,
                "unseen": {} if last_est is None else dict(last_est.unseen),
                "estimate_status": None if last_est is None else last_est.status,
                "rejected": dict(p.localizer.rejected),
                "faults": p.localizer.fault_counters(),
                "compute_s": round(p.compute_s, 4),
                "stats": {k: v for k, v in p.stats().items() if not k.startswith("rejected_")},
            }
        return {
            "time": now,
            "uptime_s": round(now - self.started, 3),
            "team": self.config.name,
            "reference": self.config.reference,
            "ros_interface": self.options.interface.kind,
            "particles": self.config.filter.particles,
            "min_particles": None
            if self.config.filter.adaptive.particle_count == "fixed"
            else min(self.config.filter.adaptive.min_particles, self.config.filter.particles),
            "methods": methods,
            "source": {
                "messages": counts["messages"],
                "rate_hz": rate("messages"),
                "events_rate_hz": {
                    k: rate(f"event.{k}") for k in ("odometry", "range", "detection")
                },
                "rejected": dict(st.rejected),
                "out_of_order": st.out_of_order,
                "restamped": sum(st.restamped.values()),
                "layouts": dict(st.layouts),
                "transport": self.source.transport.as_dict(),
                "queue_depth": self.source.queue_depth,
                "own_outputs": self.source.own_outputs,
                "buffer_depth": len(self.source.buffer),
            },
            "robots": robots,
            "onboard": self.options.robot or None,
            "hears": sorted(
                r for r in self.config.robot_names if r not in self._quiet and r in st.last_received
            ),
            "engine_errors": self.engine_errors,
            "injected_faults": {} if self.faults is None else dict(self.faults.counts),
        }

    def summary(self) -> dict[str, Any]:
        """Final figures: the status plus the totals of the run."""
        status = self.status()
        status["source"]["stats"] = self.source.stats.as_dict()
        status["events"] = self.engine.events
        status["engine_thread_cpu_s"] = round(self.engine_thread_cpu_s, 3)
        if self.recorder is not None:
            status["record"] = {"path": str(self.recorder.path), "messages": self.recorder.messages}
        status["header_time_span_s"] = (
            None
            if self.engine.t_first is None or self.engine.t_last is None
            else round(self.engine.t_last - self.engine.t_first, 3)
        )
        return status
