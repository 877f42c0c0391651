"""Sources: where the events come from.

Every source yields the same time-ordered :mod:`relloc.events`, so the engine never knows which
one it runs on:

* :mod:`relloc.sources.ingest`: the ingestion layer shared by the two that read ROS 2
  messages (routes from the team config, message-to-event conversion, header clock and
  zero-stamp restamping, reorder buffer, one stats record);
* :mod:`relloc.sources.rosbag`: rosbag2 recordings read with ``rosbags`` (the transport only);
* :mod:`relloc.sources.zenoh_source`: live robots over Eclipse Zenoh (the transport only);
* :mod:`relloc.simulator`: simulated teams, which produce events directly.
"""
