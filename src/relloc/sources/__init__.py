"""Sources: where the events come from.

Every source yields the same time-ordered :mod:`relloc.events`, so the engine never knows which
one it runs on. The recorded and simulated ones follow one protocol,
:class:`~relloc.sources.protocol.Source` (events, name, time span, counters, warnings, optional
true initial poses), and one table, :mod:`relloc.sources.table`, says which source a path names:

* :mod:`relloc.sources.ingest` (with ``clock`` and ``reorder``): the ingestion layer shared by the two that read ROS 2
  messages (routes from the team config, message-to-event conversion, header clock and
  zero-stamp restamping, reorder buffer, one stats record);
* :mod:`relloc.sources.rosbag`: rosbag2 recordings read with ``rosbags`` (the transport only;
  damaged ``.db3`` bags are read as far as readable by :mod:`relloc.sources.salvage`);
* :mod:`relloc.sources.mrclam`: the UTIAS MRCLAM data sets (text files);
* :mod:`relloc.sources.simulated`: a simulated team (:mod:`relloc.simulator`) as a source;
* :mod:`relloc.sources.zenoh_source`: live robots over Eclipse Zenoh (the transport only; pushed
  samples, no end: it shares the ingestion layer and counters, not the protocol).
"""
