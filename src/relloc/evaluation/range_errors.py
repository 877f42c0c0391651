"""Build a ranging CSV (the training CSV's columns) from a rosbag2 recording with motion capture.

The only training CSV is one session; a model that merely memorised it must be caught on
another. This turns any recording with UWB ranges and motion capture of the robots carrying the
nodes into the same columns, so ``relloc ranging eval`` can score models on it::

    timestamp,node1,node2,uwb_range,mocap_range,tb_node1_yaw,tb_node2_yaw,error

One row per UWB message between two mapped nodes: its header stamp, the nodes (as node ids,
which the loader accepts without a node map), the range, the motion-capture distance and yaws
interpolated at that stamp (header stamps on both sides: one clock), and
``error = uwb_range - mocap_range``. Messages outside the motion-capture time span are dropped
(no extrapolation).

The bag is read by :class:`~relloc.sources.rosbag.RosbagSource`, for a team made of the nodes
(each node a robot carrying it, with its motion-capture body), so the ranges and poses are the
events every other command sees: the same routes, stamps (zero stamps restamped), header order
and rejections (non-finite and non-positive ranges are dropped; ``rosbags`` only, no ROS).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from relloc.config import ConfigError, RobotConfig, TeamConfig
from relloc.events import GroundTruthEvent, RangeEvent
from relloc.ranging.dataset import CSV_COLUMNS, RangingDataError
from relloc.sources.rosbag import BagError, RosbagSource

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


def _node_team(bodies: Mapping[str, str], mocap_topic: str) -> TeamConfig:
    """A team of one robot per UWB node, named after the node and tracked by its body."""
    if len(bodies) < 2:
        raise RangingDataError(f"bodies {dict(bodies)} name fewer than two UWB nodes")
    robots = tuple(
        RobotConfig(name=node, uwb_node=node, mocap_body=b) for node, b in bodies.items()
    )
    try:
        return TeamConfig(robots=robots, reference=robots[0].name, mocap_topic=mocap_topic)
    except ConfigError as exc:
        raise RangingDataError(f"bodies {dict(bodies)}: {exc}") from None


def bag_rows(
    bag: str | Path, bodies: Mapping[str, str], mocap_topic: str = MOCAP_TOPIC
) -> list[tuple[float, str, str, float, float, float, float, float]]:
    """Rows of the ranging CSV for every UWB range between two nodes of ``bodies``."""
    team = _node_team(bodies, mocap_topic)
    ranges: list[tuple[float, str, str, float]] = []
    poses: dict[str, list[tuple[float, float, float, float]]] = {b: [] for b in bodies.values()}
    try:
        source = RosbagSource(bag, team, detections=False, odometry=False)
        for event in source:
            if isinstance(event, GroundTruthEvent):
                x, y = event.position[0], event.position[1]
                poses[bodies[event.robot]].append((event.t, x, y, event.yaw))
            elif isinstance(event, RangeEvent):
                ranges.append((event.t, event.node_a, event.node_b, event.distance))
    except BagError as exc:
        raise RangingDataError(str(exc)) from None
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
        if pa is None or pb is None:
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
