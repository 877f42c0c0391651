"""Build a ranging CSV (the training CSV's columns) from a rosbag2 recording with motion capture.

The only training CSV is one session; a model that merely memorised it must be caught on
another. This turns any recording with UWB ranges and motion capture of the robots carrying the
nodes into the same columns, so ``relloc ranging eval`` can score models on it::

    timestamp,node1,node2,uwb_range,mocap_range,tb_node1_yaw,tb_node2_yaw,error

One row per UWB message between two mapped nodes: its header stamp, the nodes (as node ids,
which the loader accepts without a node map), the range, the motion-capture distance and yaws
interpolated at that stamp (header stamps on both sides: one clock), and
``error = uwb_range - mocap_range``. Messages outside the motion-capture time span are dropped
(no extrapolation). Uses ``rosbags`` only (no ROS installation).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from relloc.ranging.dataset import CSV_COLUMNS, RangingDataError

RANGE_PREFIX = "/uwb/tof/"
MOCAP_TOPIC = "/vrpn_client_node/{body}/pose"


def parse_bodies(text: str) -> dict[str, str]:
    """``"n_7=turtlebot1_cap,n_3=turtlebot3_cap"`` -> ``{"n_7": "turtlebot1_cap", ...}``."""
    out: dict[str, str] = {}
    for item in (s.strip() for s in text.split(",")):
        node, sep, body = (s.strip() for s in item.partition("="))
        if not sep or not node or not body:
            raise RangingDataError(f"bodies item {item!r} must look like 'n_7=turtlebot1_cap'")
        out[node] = body
    return out


def _stamp(msg: object) -> float:
    stamp = msg.header.stamp  # type: ignore[attr-defined]
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def bag_rows(
    bag: str | Path, bodies: Mapping[str, str], mocap_topic: str = MOCAP_TOPIC
) -> list[tuple[float, str, str, float, float, float, float, float]]:
    """Rows of the ranging CSV for every UWB range between two nodes of ``bodies``."""
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    topic_body = {mocap_topic.format(body=b): b for b in bodies.values()}
    ranges: list[tuple[float, str, str, float]] = []
    poses: dict[str, list[tuple[float, float, float, float]]] = {b: [] for b in bodies.values()}
    try:
        reader = Reader(Path(bag))
    except Exception as exc:  # rosbags raises several types for a missing or bad bag
        raise RangingDataError(f"{bag}: cannot open as a rosbag2 recording: {exc}") from None
    with reader:
        wanted = []
        for conn in reader.connections:
            if conn.topic.startswith(RANGE_PREFIX):
                parts = conn.topic[len(RANGE_PREFIX) :].split("/")
                if len(parts) >= 2 and parts[0] in bodies and parts[1] in bodies:
                    wanted.append(conn)
            elif conn.topic in topic_body:
                wanted.append(conn)
        for conn, _, raw in reader.messages(connections=wanted):
            msg = typestore.deserialize_cdr(raw, conn.msgtype)
            if conn.topic in topic_body:
                q = msg.pose.orientation
                yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
                poses[topic_body[conn.topic]].append(
                    (_stamp(msg), msg.pose.position.x, msg.pose.position.y, yaw)
                )
            else:
                a, b = conn.topic[len(RANGE_PREFIX) :].split("/")[:2]
                ranges.append((_stamp(msg), a, b, float(msg.range)))
    missing = [b for b, p in poses.items() if not p]
    if missing:
        raise RangingDataError(f"{bag}: no motion capture for {missing} on {mocap_topic}")
    if not ranges:
        raise RangingDataError(f"{bag}: no UWB range between the nodes {sorted(bodies)}")
    track = {b: np.asarray(sorted(p)) for b, p in poses.items()}

    def at(body: str, t: float) -> tuple[float, float, float] | None:
        arr = track[body]
        if not arr[0, 0] <= t <= arr[-1, 0]:
            return None
        x = float(np.interp(t, arr[:, 0], arr[:, 1]))
        y = float(np.interp(t, arr[:, 0], arr[:, 2]))
        c = float(np.interp(t, arr[:, 0], np.cos(arr[:, 3])))
        s = float(np.interp(t, arr[:, 0], np.sin(arr[:, 3])))
        return x, y, math.atan2(s, c)

    rows = []
    for t, a, b, rng in sorted(ranges):
        pa, pb = at(bodies[a], t), at(bodies[b], t)
        if pa is None or pb is None or not math.isfinite(rng):
            continue
        dist = math.hypot(pa[0] - pb[0], pa[1] - pb[1])
        rows.append((t, a, b, rng, dist, pa[2], pb[2], rng - dist))
    return rows


def write_csv(
    rows: list[tuple[float, str, str, float, float, float, float, float]], out: str | Path
) -> None:
    """Write rows with the training CSV's header."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_COLUMNS)
        writer.writerows(rows)
