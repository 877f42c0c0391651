"""Faults injected into ROS 2 messages on their way out (``relloc replay --drop ...``).

:mod:`relloc.faults` transforms relloc events. A replay publishes a bag's raw CDR messages, so
here each message of a team topic (odometry, UWB ranges, motion capture, detections) is
decoded, turned into its event as the ingestion layer would (:mod:`relloc.ros.messages`), put
through the same :class:`~relloc.faults.FaultInjector`, and, if the fault changed it, the
changed fields are written back into the decoded message and it is encoded again; every other
field (covariances, twist, frame ids) is kept. A message the fault leaves alone goes out as the
very bytes of the bag, and a topic that is not the team's is never touched.

Times are the stream's: a message's header stamp. A topic recorded with zero stamps (restamped
on arrival by the server, ``odom_zero_stamps``) is timed by its receive time plus the offset of
the stamped topics seen so far, and a stamp fault leaves its zero stamp alone (the server would
restamp it anyway). A kidnapping needs the robots' ground truth: motion-capture messages go
through the injector even when they are not published.
"""

from __future__ import annotations

import dataclasses
import statistics
from collections import deque
from typing import Any

from relloc.config import TeamConfig
from relloc.events import DetectionEvent, Event, GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.faults import FaultInjector, Faults
from relloc.ros.messages import (
    decode,
    encode,
    odometry_to_event,
    pose_to_ground_truth,
    quaternion_from_yaw,
    range_to_event,
    stamp_to_sec,
    time_msg,
)
from relloc.sources.ingest import Route, team_routes

__all__ = ["MessageFaults"]

_OFFSETS = 50
"""Stamped messages whose (stamp - receive time) median times the zero-stamp topics."""


class MessageFaults:
    """``faults(topic, msgtype, raw, received)``: the payload to publish, or ``None`` if the
    message is lost (module docstring). ``counts`` says what was done (``dropped``,
    ``silenced``, ``shifted``, ``changed``)."""

    def __init__(self, config: TeamConfig, faults: Faults) -> None:
        self.injector = FaultInjector(faults)
        self.routes: dict[str, Route] = {
            r.topic: r for r in team_routes(config, ground_truth=True) if r.kind in _KINDS
        }
        self._offsets: deque[float] = deque(maxlen=_OFFSETS)

    @property
    def counts(self) -> dict[str, int]:
        return self.injector.counts

    def topics(self) -> set[str]:
        """The topics this transform reads (the team's; motion capture among them)."""
        return set(self.routes)

    def __call__(self, topic: str, msgtype: str, raw: bytes, received: float) -> bytes | None:
        route = self.routes.get(topic)
        if route is None:
            return raw
        msg = decode(raw, msgtype)
        stamp = stamp_to_sec(msg.header.stamp)
        zero = stamp == 0.0 or route.zero_stamps
        if zero:
            t = received + (statistics.median(self._offsets) if self._offsets else 0.0)
        else:
            t = stamp
            self._offsets.append(stamp - received)
        event = _event(route, msg, t)
        out = self.injector(event)
        if out is None:
            return None
        if out == event:
            return raw
        self.counts["changed"] = self.counts.get("changed", 0) + 1
        return encode(_written_back(msg, event, out, zero), msgtype)


_KINDS = ("odometry", "range", "ground_truth", "detection")


def _event(route: Route, msg: Any, t: float) -> Event:
    if route.kind == "odometry":
        return odometry_to_event(msg, route.robot, t=t)
    if route.kind == "range":
        return range_to_event(msg, route.robot, route.robot_b, node_a=route.node_a, node_b=route.node_b, t=t)
    if route.kind == "ground_truth":
        return pose_to_ground_truth(msg, route.robot, t=t)
    return DetectionEvent(t, route.robot)  # what a loss or a silence needs of a detection


def _written_back(msg: Any, before: Event, after: Event, zero_stamp: bool) -> Any:
    """``msg`` with the fields the fault changed (``before`` -> ``after``) set to their new
    values."""
    if after.t != before.t and not zero_stamp:
        msg = dataclasses.replace(msg, header=dataclasses.replace(msg.header, stamp=time_msg(after.t)))
    if isinstance(after, RangeEvent) and isinstance(before, RangeEvent) and after.distance != before.distance:
        msg = dataclasses.replace(msg, range=after.distance)
    elif isinstance(after, OdometryEvent) and isinstance(before, OdometryEvent):
        pose = msg.pose.pose
        if (after.x, after.y) != (before.x, before.y):
            position = dataclasses.replace(pose.position, x=after.x, y=after.y)
            pose = dataclasses.replace(pose, position=position)
        if after.yaw != before.yaw:
            pose = dataclasses.replace(pose, orientation=quaternion_from_yaw(after.yaw))
        msg = dataclasses.replace(msg, pose=dataclasses.replace(msg.pose, pose=pose))
    elif isinstance(after, GroundTruthEvent) and (after.x, after.y) != (getattr(before, "x", 0.0), getattr(before, "y", 0.0)):
        position = dataclasses.replace(msg.pose.position, x=after.x, y=after.y)
        msg = dataclasses.replace(msg, pose=dataclasses.replace(msg.pose, position=position))
    return msg
