"""UWB ranges recorded as a driver's node frames (one topic per node listing its peers), for
drafting a team config from a bag without ``sensor_msgs/msg/Range`` topics.

:func:`relloc.sources.inspect_bag.inspect_bag` reads ranges of one node pair per topic. A
LinkTrack team (``nlink_parser/msg/LinktrackNodeframe2`` on ``/n<k>/range``, the MURP quadrotor
recordings) publishes one frame per node instead, listing each peer's id and distance.
:func:`with_node_frames` fills an inventory that found no pair topics from such frames: the
publishing node is the last number in its topic's name (``/n3/range`` -> ``3``, pattern
``/n{a}/range``), as a team config's ``range_topic`` names it, and each peer's id is as the
frames list it. The types and field paths known are :data:`NODE_FRAMES`; the type's definition
comes from the bag (rosbag2 stores it) or one already registered.
"""

from __future__ import annotations

import math
import re
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from relloc.config import UwbConfig
from relloc.events import pair_key
from relloc.ros.messages import MessageDecodeError, decode, stamp_to_sec
from relloc.sensors.range_fields import RangeFields
from relloc.sources.inspect_bag import BagInventory
from relloc.sources.rosbag import _bag_layouts, _open_reader

__all__ = ["NODE_FRAMES", "NodeFrames", "with_node_frames"]


@dataclass(frozen=True)
class NodeFrames:
    """Where a node frame type keeps its peers' distances and ids (``[uwb]`` field paths)."""

    distance_field: str
    peer_field: str


NODE_FRAMES: dict[str, NodeFrames] = {
    "nlink_parser/msg/LinktrackNodeframe2": NodeFrames("nodes[].dis", "nodes[].id"),
}
"""Node frame types :func:`with_node_frames` reads, by ROS type name."""

_LAST_NUMBER = re.compile(r"^(?P<pre>.*?)(?P<node>\d+)(?P<post>\D*)$")


def frame_fields(inv: BagInventory) -> NodeFrames | None:
    """The field paths of the node frames ``inv`` read its ranges from, or ``None``."""
    return NODE_FRAMES.get(inv.range_type)


def with_node_frames(bag: Path, inv: BagInventory) -> BagInventory:
    """``inv`` with its ranges read from node frames of :data:`NODE_FRAMES`, when it found no
    range topic and the bag has such frames on topics naming their node; else ``inv`` as it is."""
    if inv.ranges:
        return inv
    found = [
        (t, ty, m)
        for t, ty in inv.topics.items()
        if ty in NODE_FRAMES and (m := _LAST_NUMBER.match(t))
    ]
    if not found:
        return inv
    patterns: dict[str, list[str]] = defaultdict(list)
    for topic, msgtype, m in found:
        patterns[f"{msgtype} {m['pre']}{{a}}{m['post']}"].append(topic)
    key = max(sorted(patterns), key=lambda p: len(patterns[p]))
    msgtype, _, pattern = key.partition(" ")
    node_of = {t: _LAST_NUMBER.match(t)["node"] for t in patterns[key]}  # type: ignore[index]
    spec = NODE_FRAMES[msgtype]
    rows: dict[str, list[tuple[float, float]]] = defaultdict(list)
    counts: dict[str, int] = defaultdict(int)
    messages = 0
    with _open_reader(Path(bag)) as reader:
        _bag_layouts(reader)  # registers the frame type from the bag's definition
        fields = RangeFields.of(
            UwbConfig(
                range_type=msgtype,
                distance_field=spec.distance_field,
                peer_field=spec.peer_field,
            )
        )
        conns = [c for c in reader.connections if c.topic in node_of]
        for conn, recv_ns, raw in reader.messages(conns):
            try:
                msg = decode(raw, conn.msgtype)
            except MessageDecodeError:
                continue
            messages += 1
            stamp = stamp_to_sec(msg.header.stamp) if fields.header else 0.0
            t = stamp if stamp != 0.0 else recv_ns * 1e-9
            node = node_of[conn.topic]
            for peer, distance in fields.ranges(msg):
                if peer == node:
                    continue
                counts[node] += 1
                counts[peer] += 1
                if math.isfinite(distance) and distance > 0.0:
                    rows[pair_key(node, peer)].append((t, distance))
    ranges = {}
    for pair, v in rows.items():
        arr = np.array(v, dtype=float).reshape(-1, 2)
        ranges[pair] = arr[np.argsort(arr[:, 0], kind="stable")]
    return replace(
        inv,
        range_pattern=pattern,
        range_type=msgtype,
        range_layout="",
        ranges=ranges,
        range_counts=dict(counts),
        range_messages=messages,
    )
