"""The live engine over Eclipse Zenoh: ``relloc serve``, ``relloc replay``.

``serve`` runs the *same* :class:`~relloc.engine.Engine` and method pipelines as ``relloc run``
and the demo, fed by :class:`~relloc.sources.zenoh_source.ZenohSource` (the robots' ROS 2
topics as bridged by zenoh-bridge-ros2dds) and publishing through
:class:`~relloc.sinks.zenoh_sink.ZenohSink`. One thread runs the engine; Zenoh's callbacks only
enqueue. ``replay`` publishes a rosbag2 recording's raw CDR messages on the bridge's keys at
the recorded pace (times ``--rate``), so a recording stands in for the robots;
``relloc bench resources`` (:mod:`relloc.bench_resources`) runs both on loopback and measures the server process (CPU, peak RSS,
end-to-end latency). ``docs/live.md`` tells the whole story and gives the measured figures.

Latency is traced, not guessed: the replay attaches its send wall time to every message
(:func:`~relloc.sources.zenoh_source.encode_sent_time`); the server, run with ``--trace``,
publishes for each estimate the message whose arrival produced it (its key, header stamp and
send/receive times) and the estimate's publication time on ``relloc/trace``. Both ends share the
host's wall clock on loopback.

=======================  ==================================================================
:mod:`.session`          Zenoh session options and the live commands' ``--mode/--connect/...``
:mod:`.server`           :class:`LiveServer` (the engine loop) and :class:`ServeOptions`
:mod:`.publish`          :func:`replay_bag`, :func:`publish_events`: data into Zenoh
:mod:`.collect`          :class:`EstimateCollector`, :func:`ape_against_bag` (tests, benchmarks)
:mod:`.cli`              the ``serve`` and ``replay`` commands
=======================  ==================================================================
"""

from relloc.live.cli import register
from relloc.live.collect import SHORTBAG, EstimateCollector, ape_against_bag
from relloc.live.publish import (
    SIM_TIME_BASE,
    PublishStats,
    ReplayOptions,
    event_messages,
    publish_events,
    replay_bag,
    simulated_team,
)
from relloc.live.server import LiveServer, ServeOptions
from relloc.live.session import (
    ZenohOptions,
    add_zenoh_args,
    free_tcp_port,
    open_cli_session,
    open_session,
    zenoh_options_from_args,
)

__all__ = [
    "SHORTBAG",
    "SIM_TIME_BASE",
    "EstimateCollector",
    "LiveServer",
    "PublishStats",
    "ReplayOptions",
    "ServeOptions",
    "ZenohOptions",
    "add_zenoh_args",
    "ape_against_bag",
    "event_messages",
    "free_tcp_port",
    "open_cli_session",
    "open_session",
    "publish_events",
    "register",
    "replay_bag",
    "simulated_team",
    "zenoh_options_from_args",
]
