"""Collecting what a server published, and scoring it against a recording's motion capture.

For tests and benchmarks: :class:`EstimateCollector` rebuilds the estimates from the very pose
messages any ROS consumer would receive; :func:`ape_against_bag` scores them as ``relloc run``
does.
"""

from __future__ import annotations

import json
import logging
import math
import statistics
import threading
import time
from pathlib import Path
from typing import Any

from relloc.config import TeamConfig
from relloc.estimate import BODY_FRAME, HEADING_FRAME, Estimate
from relloc.ros.interfaces import RosInterface
from relloc.ros.messages import POSE_WITH_COVARIANCE_STAMPED
from relloc.ros.zenoh_node import ZenohNode
from relloc.sinks.zenoh_sink import STRING, pose_topic

__all__ = ["EstimateCollector", "ape_against_bag"]

log = logging.getLogger(__name__)


class EstimateCollector:
    """Subscribes to a server's pose (and trace) topics and rebuilds the estimates it published.

    For tests and benchmarks: the same messages any ROS consumer would get, on the interface's
    keys. Messages are decoded on Zenoh's threads into lists guarded by a lock.
    """

    def __init__(
        self,
        session: Any,
        config: TeamConfig,
        *,
        prefix: str = "relloc",
        method: str = "pf",
        primary: bool = True,
        interface: RosInterface | None = None,
    ) -> None:
        self.config = config
        self.method = method
        self.interface = iface = interface or RosInterface()
        self._lock = threading.Lock()
        self._poses: list[
            tuple[int, int, str, float, float, tuple[float, float, float, float], str]
        ] = []
        self._traces: list[dict[str, Any]] = []
        self.node = ZenohNode(session, iface, "relloc_collector")
        for robot in config.others:
            topic = pose_topic(prefix, robot, None if primary else method)
            channel = iface.channel(topic, POSE_WITH_COVARIANCE_STAMPED)

            def on_pose(sample: Any, robot: str = robot) -> None:
                self._on_pose(robot, sample)

            self.node.subscribe(channel, on_pose)
        self.node.subscribe(iface.channel(f"{prefix.strip('/')}/trace", STRING), self._on_trace)

    def _on_pose(self, robot: str, sample: Any) -> None:
        from relloc.ros.messages import decode

        msg = decode(sample.payload.to_bytes(), POSE_WITH_COVARIANCE_STAMPED)
        c = msg.pose.covariance
        p = msg.pose.pose.position
        item = (
            int(msg.header.stamp.sec),
            int(msg.header.stamp.nanosec),
            robot,
            float(p.x),
            float(p.y),
            (float(c[0]), float(c[1]), float(c[6]), float(c[7])),
            str(msg.header.frame_id),
        )
        with self._lock:
            self._poses.append(item)

    def _on_trace(self, sample: Any) -> None:
        record = json.loads(self.interface.decode_text(sample.payload.to_bytes()))
        record["received"] = time.time()
        with self._lock:
            self._traces.append(record)

    def estimates(self) -> list[Estimate]:
        """The published estimates, one per stamp, in time order."""
        with self._lock:
            poses = list(self._poses)
        grouped: dict[tuple[int, int], dict[str, Any]] = {}
        for sec, nsec, robot, x, y, cov, frame_id in poses:
            grouped.setdefault((sec, nsec), {})[robot] = (x, y, cov, frame_id)
        out = []
        for (sec, nsec), robots in sorted(grouped.items()):
            out.append(
                Estimate(
                    t=sec + nsec * 1e-9,
                    method=self.method,
                    reference=self.config.reference,
                    positions={r: (v[0], v[1]) for r, v in robots.items()},
                    covariances={
                        r: ((v[2][0], v[2][1]), (v[2][2], v[2][3])) for r, v in robots.items()
                    },
                    frame=BODY_FRAME
                    if any(v[3].endswith("/base_link") for v in robots.values())
                    else HEADING_FRAME,
                )
            )
        return out

    def traces(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self._traces)

    def close(self) -> None:
        self.node.close()


def ape_against_bag(
    estimates: list[Estimate],
    bag: Path,
    config: TeamConfig,
    *,
    warmup: float = 5.0,
    t0: float | None = None,
) -> dict[str, Any]:
    """APE of estimates against the motion capture of a bag (the ``relloc run`` definition).

    ``t0`` is the start of the warm-up window (default: the bag's first motion-capture stamp).
    Returns per robot ``{"median", "rmse", "max", "n"}`` and ``"mean_median"``.
    """
    from relloc.evaluation.metrics import ApeStats, GroundTruth, after, associate
    from relloc.events import GroundTruthEvent
    from relloc.sources.rosbag import RosbagSource

    gt = GroundTruth(config.reference)
    source = RosbagSource(bag, config, detections=False, ranges=False, odometry=False)
    first = None
    for ev in source:
        if isinstance(ev, GroundTruthEvent):
            first = ev.t if first is None else first
            gt.add(ev)
    start = (t0 if t0 is not None else (first or 0.0)) + warmup
    paired = associate(estimates, gt, config.others)
    out: dict[str, Any] = {}
    medians = []
    for robot, p in paired.items():
        s = ApeStats.of(after(p, start).errors)
        out[robot] = {"median": s.median, "rmse": s.rmse, "max": s.max, "n": s.n}
        if s.n:
            medians.append(s.median)
    out["mean_median"] = statistics.fmean(medians) if medians else math.nan
    return out
