"""A simulated flight written as a recording laid out as the MURP quadrotor recordings.

Motion capture as ``geometry_msgs/msg/PoseStamped`` on ``/<body>/world`` (the body named as its
robot) and each tag's ranges as LinkTrack node frames (``nlink_parser/msg/LinktrackNodeframe2``,
one peer a frame) on ``/n<id>/range``, tags numbered from 1 in the order the robots list them:
what ``relloc init`` drafts a flying team from. Nothing else is written (no odometry, no
heights: what such a recording holds), so a drafted run on it takes every step a recording of
that layout takes (``scripts/flight_bag_runs.py``).

The LinkTrack message types are a driver's, not the package's: ``msg_dirs`` names the folder of
their ``.msg`` files (``examples/uwb_drivers/linktrack_ros2`` in the repository).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from relloc.events import GroundTruthEvent, RangeEvent
from relloc.ros import messages as rm
from relloc.ros.stores import custom_types, register_types
from relloc.simulator.flight import FlightSimulation

LINKTRACK_FRAME = "nlink_parser/msg/LinktrackNodeframe2"
T0 = 1_700_000_000.0
"""The recording's first stamp (s since the epoch): a bag's clock, not the simulator's zero."""


def tag_ids(sim: FlightSimulation) -> dict[str, int]:
    """Each simulated tag's LinkTrack id: 1, 2, ... in the order the robots list their tags."""
    nodes = [t.node for r in sim.config.robots for t in r.tags]
    return {node: k + 1 for k, node in enumerate(nodes)}


def write_flight_bag(
    path: Path, sim: FlightSimulation, msg_dirs: Path, ids: dict[str, int] | None = None
) -> dict[str, tuple[float, ...]]:
    """Write ``sim`` as a rosbag2 folder at ``path`` (sqlite3); the true lever arm of each
    LinkTrack id (``ids``: the simulation's tag -> its id, :func:`tag_ids` by default)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    register_types(custom_types(msg_dirs))
    ids = ids or tag_ids(sim)
    store = rm.typestore()
    node_type = store.types["nlink_parser/msg/LinktrackNode2"]
    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        conns: dict[str, Any] = {}

        def put(topic: str, msgtype: str, t: float, msg: Any) -> None:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(conns[topic], round(t * 1e9), rm.encode(msg, msgtype))

        frame = rm.zero_message(LINKTRACK_FRAME)
        for ev in sim.events():
            t = ev.t + T0
            if isinstance(ev, GroundTruthEvent):
                pose = rm.pose_stamped_msg(dataclasses.replace(ev, t=t))
                put(f"/{ev.robot}/world", rm.POSE_STAMPED, t, pose)
            elif isinstance(ev, RangeEvent):
                a, b = ids[ev.node_a], ids[ev.node_b]
                peer = node_type(role=1, id=b, dis=ev.distance, fp_rssi=0.0, rx_rssi=0.0)
                header = dataclasses.replace(frame.header, stamp=rm.time_msg(t))
                msg = dataclasses.replace(frame, id=a, nodes=[peer], header=header)
                put(f"/n{a}/range", LINKTRACK_FRAME, t, msg)
    return {str(ids[n]): arm for n, arm in sim.lever_arms.items()}
