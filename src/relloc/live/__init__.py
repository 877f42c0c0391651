"""The live engine over Eclipse Zenoh (the ``relloc serve`` and ``replay`` commands: :mod:`relloc.cli.live`).

``serve`` runs the *same* :class:`~relloc.engine.Engine` and method pipelines as ``relloc run``
and the demo, fed by :class:`~relloc.sources.zenoh_source.ZenohSource` (the robots' ROS 2
topics as bridged by zenoh-bridge-ros2dds, or as robots on rmw_zenoh publish them:
:mod:`relloc.ros.interfaces`) and publishing through
:class:`~relloc.sinks.zenoh_sink.ZenohSink`. One thread runs the engine; Zenoh's callbacks only
enqueue. ``replay`` publishes a rosbag2 recording's raw CDR messages on the interface's keys at
the recorded pace (times ``--rate``), so a recording stands in for the robots;
``benchmarks/serve_resources.py`` runs both on loopback and measures the server process (CPU,
peak RSS, end-to-end latency). ``docs/explanation/live-engine.md`` tells the whole story.

The derivation: docs/explanation/internals.md, section ``relloc.live``.
"""

from relloc.live.collect import EstimateCollector, ape_against_bag
from relloc.live.message_faults import MessageFaults
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
    free_tcp_port,
    open_session,
)

__all__ = [
    "SIM_TIME_BASE",
    "EstimateCollector",
    "LiveServer",
    "MessageFaults",
    "PublishStats",
    "ReplayOptions",
    "ServeOptions",
    "ZenohOptions",
    "ape_against_bag",
    "event_messages",
    "free_tcp_port",
    "open_session",
    "publish_events",
    "replay_bag",
    "simulated_team",
]
