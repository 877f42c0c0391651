"""The built-in sensors: odometry, UWB ranges, detections, teammate sightings, motion capture.

Each descriptor says what its topics are in the team config and how their messages become
events (and, for replay and faults, messages again); :mod:`relloc.sensors.base` explains the
fields. They are registered in the order routes are listed: per robot odometry, motion capture
and detections; then the sightings' topics, extra motion-capture objects and the UWB pairs.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Hashable, Iterable, Sequence
from itertools import combinations
from typing import Any, ClassVar, Literal

from relloc.config import ConfigError, RobotConfig, TeamConfig
from relloc.events import (
    DetectionEvent,
    Event,
    GroundTruthEvent,
    OdometryEvent,
    RangeEvent,
    SightingEvent,
)
from relloc.filter.ranges import RangeBatch
from relloc.filter.sightings import SightingBatch
from relloc.ros.cdr import decode_odometry, decode_range
from relloc.ros.distros import Layout
from relloc.ros.messages import (
    MOCAP_TYPES,
    ODOMETRY,
    POINT_STAMPED,
    POSE_ARRAY,
    POSE_STAMPED,
    RANGE,
    SPATIAL_DETECTION_ARRAY,
    detections_to_event,
    odometry_msg,
    odometry_to_event,
    point_to_sighting,
    pose_stamped_msg,
    pose_to_ground_truth,
    quaternion_from_yaw,
    range_msg,
    range_rejection,
    range_to_event,
)
from relloc.sensors.base import Conversion, Route, Sensor, Switch
from relloc.sensors.range_fields import RangeFields, load_range_type

__all__ = [
    "DETECTION",
    "DETECTION_TYPES",
    "GROUND_TRUTH",
    "ODOMETRY_SENSOR",
    "RANGE_SENSOR",
    "SIGHTING",
    "match_range_topics",
]

DETECTION_TYPES: dict[str, tuple[str, ...]] = {
    "depthai": (SPATIAL_DETECTION_ARRAY,),
    "posearray": (POSE_ARRAY,),
    "": (SPATIAL_DETECTION_ARRAY, POSE_ARRAY),
}
"""Message types a robot's ``detection_format`` accepts (unspecified: both, tried in order)."""


class Odometry(Sensor):
    """Each robot's ``odom_topic``: ``nav_msgs/Odometry`` -> :class:`OdometryEvent`."""

    kind: ClassVar[str] = "odometry"
    event: ClassVar[type] = OdometryEvent
    msgtypes: ClassVar[tuple[str, ...]] = (ODOMETRY,)
    switch: ClassVar[Switch | None] = "odometry"
    wake: ClassVar[Literal["odometry", "measurement"] | None] = "odometry"
    essential: ClassVar[bool] = True
    faulted: ClassVar[bool] = True

    def robot_routes(self, config: TeamConfig, robot: RobotConfig) -> list[Route]:
        if not robot.odom_topic:
            return []
        what = f"odometry of {robot.name}"
        return [
            Route(
                robot.odom_topic,
                self.kind,
                (ODOMETRY,),
                robot.name,
                what,
                zero_stamps=robot.odom_zero_stamps,
            )
        ]

    def fast(self, payload: bytes, layout: Layout) -> tuple[float, ...] | None:
        return decode_odometry(payload)

    def convert(
        self,
        route: Route,
        stream: str,
        msg: Any,
        fast: tuple[float, ...] | None,
        stamp: float,
        ingest: Conversion,
    ) -> Event | None:
        if fast is not None:
            _, x, y, yaw, v, w, z = fast
            return OdometryEvent(t=stamp, robot=route.robot, x=x, y=y, yaw=yaw, v=v, w=w, z=z)
        return odometry_to_event(msg, route.robot, t=stamp)

    def message(self, event: OdometryEvent) -> Any:
        return odometry_msg(event)

    def fault_event(self, route: Route, msg: Any, t: float) -> Event:
        return odometry_to_event(msg, route.robot, t=t)

    def write_back(self, msg: Any, before: Any, after: Any) -> Any:
        pose = msg.pose.pose
        if (after.x, after.y) != (before.x, before.y):
            position = dataclasses.replace(pose.position, x=after.x, y=after.y)
            pose = dataclasses.replace(pose, position=position)
        if after.yaw != before.yaw:
            pose = dataclasses.replace(pose, orientation=quaternion_from_yaw(after.yaw))
        return dataclasses.replace(msg, pose=dataclasses.replace(msg.pose, pose=pose))


class Sighting(Sensor):
    """Per observer with a ``sighting_topic`` template (``{target}``) and per teammate:
    ``geometry_msgs/PointStamped`` in the observer's body frame -> :class:`SightingEvent`."""

    kind: ClassVar[str] = "sighting"
    event: ClassVar[type] = SightingEvent
    msgtypes: ClassVar[tuple[str, ...]] = (POINT_STAMPED,)
    model = SightingBatch
    switch: ClassVar[Switch | None] = "detections"
    required: ClassVar[bool] = False
    wake: ClassVar[Literal["odometry", "measurement"] | None] = "measurement"

    def team_routes(self, config: TeamConfig) -> list[Route]:
        routes = []
        for robot in config.robots:
            if not robot.sighting_topic:
                continue
            if "{target}" not in robot.sighting_topic:
                raise ConfigError(
                    f"{robot.name}: sighting_topic {robot.sighting_topic!r} must contain {{target}}"
                )
            sigma = (robot.sighting_sigma_range, math.radians(robot.sighting_sigma_bearing_deg))
            for other in config.robots:
                if other.name != robot.name:
                    topic = robot.sighting_topic.format(target=other.name)
                    what = f"sightings of {other.name} by {robot.name}"
                    routes.append(
                        Route(
                            topic,
                            self.kind,
                            (POINT_STAMPED,),
                            robot.name,
                            what,
                            robot_b=other.name,
                            sigma=sigma,
                        )
                    )
        return routes

    def convert(
        self,
        route: Route,
        stream: str,
        msg: Any,
        fast: tuple[float, ...] | None,
        stamp: float,
        ingest: Conversion,
    ) -> Event | None:
        return point_to_sighting(msg, route.robot, route.robot_b, *route.sigma, t=stamp)


class GroundTruth(Sensor):
    """Motion capture (``mocap_topic`` with ``{body}``) of each robot's ``mocap_body`` and of
    extra objects: ``geometry_msgs/PoseStamped`` (or another of
    :data:`~relloc.ros.messages.MOCAP_TYPES`, read only: replay and faults write PoseStamped)
    -> :class:`GroundTruthEvent` (evaluation only)."""

    kind: ClassVar[str] = "ground_truth"
    event: ClassVar[type] = GroundTruthEvent
    msgtypes: ClassVar[tuple[str, ...]] = (POSE_STAMPED,)
    switch: ClassVar[Switch | None] = "ground_truth"
    faulted: ClassVar[bool] = True

    def robot_routes(self, config: TeamConfig, robot: RobotConfig) -> list[Route]:
        if not robot.mocap_body:
            return []
        topic = config.mocap_topic.format(body=robot.mocap_body)
        return [Route(topic, self.kind, MOCAP_TYPES, robot.name, f"motion capture of {robot.name}")]

    def object_routes(self, config: TeamConfig, objects: Sequence[str]) -> list[Route]:
        return [
            Route(
                config.mocap_topic.format(body=body),
                self.kind,
                MOCAP_TYPES,
                body,
                f"motion capture of object {body}",
            )
            for body in objects
        ]

    def convert(
        self,
        route: Route,
        stream: str,
        msg: Any,
        fast: tuple[float, ...] | None,
        stamp: float,
        ingest: Conversion,
    ) -> Event | None:
        return pose_to_ground_truth(msg, route.robot, t=stamp)

    def message(self, event: GroundTruthEvent) -> Any:
        return pose_stamped_msg(event)

    def fault_event(self, route: Route, msg: Any, t: float) -> Event:
        return pose_to_ground_truth(msg, route.robot, t=t)

    def write_back(self, msg: Any, before: Any, after: Any) -> Any:
        if after.position == before.position:
            return msg
        x, y = after.position[0], after.position[1]  # faults move a robot in the plane
        position = dataclasses.replace(msg.pose.position, x=x, y=y)
        return dataclasses.replace(msg, pose=dataclasses.replace(msg.pose, position=position))


class Detection(Sensor):
    """Each robot's ``detection_topic`` (``detection_format``): spatial detections ->
    :class:`DetectionEvent` in the body frame (the camera extrinsics applied). No model of its
    own: the association stage turns pairs of them into relative observations."""

    kind: ClassVar[str] = "detection"
    event: ClassVar[type] = DetectionEvent
    msgtypes: ClassVar[tuple[str, ...]] = (SPATIAL_DETECTION_ARRAY, POSE_ARRAY)
    switch: ClassVar[Switch | None] = "detections"
    faulted: ClassVar[bool] = True

    def robot_routes(self, config: TeamConfig, robot: RobotConfig) -> list[Route]:
        if not robot.detection_topic:
            return []
        fmt = robot.detection_format
        what = f"detections of {robot.name} ({fmt or 'any'})"
        return [
            Route(
                robot.detection_topic,
                self.kind,
                DETECTION_TYPES[fmt],
                robot.name,
                what,
                camera=robot.camera,
            )
        ]

    def convert(
        self,
        route: Route,
        stream: str,
        msg: Any,
        fast: tuple[float, ...] | None,
        stamp: float,
        ingest: Conversion,
    ) -> Event | None:
        assert route.camera is not None
        det, rejected = detections_to_event(msg, route.robot, route.camera, t=stamp)
        for reason, n in rejected.items():
            ingest.stats.rejected[f"detection_{reason}"] += n
        return det

    def fault_event(self, route: Route, msg: Any, t: float) -> Event:
        return DetectionEvent(t, route.robot)  # what a loss or a silence needs of a detection


class Range(Sensor):
    """UWB ranges on ``uwb.range_topic``. With ``sensor_msgs/msg/Range`` (or any type holding
    one range, ``uwb.distance_field``) the template has ``{a}``/``{b}`` = node ids, for every
    pair of the team's robots and in both node orders (a UWB driver may publish either). With
    a type listing peers (``uwb.peer_field``, :mod:`relloc.sensors.range_fields`) it has
    ``{a}`` (the publishing node) or ``{robot}``, one topic per node. Either way each range is a
    :class:`RangeEvent` carrying both robots and both nodes; a peer no robot carries is counted
    (``range_unknown_peer``), and a range equal to the previous one of its topic and peer passes
    and is counted in ``repeated_ranges``."""

    kind: ClassVar[str] = "range"
    event: ClassVar[type] = RangeEvent
    msgtypes: ClassVar[tuple[str, ...]] = (RANGE,)
    model = RangeBatch
    switch: ClassVar[Switch | None] = "ranges"
    required: ClassVar[bool] = False
    warn_empty: ClassVar[bool] = False
    wake: ClassVar[Literal["odometry", "measurement"] | None] = "measurement"
    essential: ClassVar[bool] = True
    faulted: ClassVar[bool] = True

    def team_routes(self, config: TeamConfig) -> list[Route]:
        uwb = config.uwb
        load_range_type(uwb)
        fields = RangeFields.of(uwb)
        _check_range_template(uwb.range_topic, peers=bool(fields.peer))
        tags = [(r.name, node) for r in config.robots for node in r.nodes]
        nodes = {node: robot for robot, node in tags}
        base: dict[str, Any] = {
            "kind": self.kind,
            "msgtypes": (uwb.range_type,),
            "stamped": fields.header,
            "params": (fields, nodes),
        }
        if fields.peer:
            return [
                Route(
                    uwb.range_topic.format(a=node, robot=robot),
                    robot=robot,
                    what=f"UWB ranges of {node}",
                    node_a=node,
                    **base,
                )
                for robot, node in tags
            ]
        routes = []
        for (ra, na), (rb, nb) in combinations(tags, 2):
            if ra == rb:
                continue  # two tags of one robot: their range is a constant of its body
            for (r1, n1), (r2, n2) in (((ra, na), (rb, nb)), ((rb, nb), (ra, na))):
                routes.append(
                    Route(
                        uwb.range_topic.format(a=n1, b=n2),
                        robot=r1,
                        what=f"UWB ranges {n1}-{n2}",
                        robot_b=r2,
                        node_a=n1,
                        node_b=n2,
                        **base,
                    )
                )
        return routes

    def fast(self, payload: bytes, layout: Layout) -> tuple[float, ...] | None:
        if layout.msgtype != RANGE:
            return None
        return decode_range(payload, "variance" in layout.fields)

    def convert(
        self,
        route: Route,
        stream: str,
        msg: Any,
        fast: tuple[float, ...] | None,
        stamp: float,
        ingest: Conversion,
    ) -> Event | list[Event] | None:
        if fast is not None:
            return self._event(route, stream, "", fast[1], stamp, ingest)
        fields, nodes = route.params
        events: list[Event] = []
        for peer, distance in fields.ranges(msg):
            robot_b = nodes.get(peer) if peer else route.robot_b
            if robot_b is None or robot_b == route.robot:
                ingest.reject(
                    "range_unknown_peer" if robot_b is None else "range_self",
                    stream,
                    f"node {peer!r}",
                )
                continue
            event = self._event(route, stream, peer, distance, stamp, ingest, robot_b)
            if event is not None:
                events.append(event)
        return events

    def _event(
        self,
        route: Route,
        stream: str,
        peer: str,
        distance: float,
        stamp: float,
        ingest: Conversion,
        robot_b: str = "",
    ) -> RangeEvent | None:
        reason = range_rejection(distance)
        if reason is not None:
            ingest.reject(f"range_{reason}", stream)
            return None
        last = ingest.memory(self.kind)
        if last.get((route.topic, peer)) == distance:
            ingest.stats.repeated_ranges += 1
        last[(route.topic, peer)] = distance
        return RangeEvent(
            t=stamp, robot_a=route.robot, robot_b=robot_b or route.robot_b, distance=distance, node_a=route.node_a,
            node_b=peer or route.node_b,
        )  # fmt: skip

    def message(self, event: RangeEvent) -> Any:
        return range_msg(event)

    def channel_key(self, route: Route) -> Hashable:
        return (route.node_a, route.node_b)

    def event_key(self, event: RangeEvent) -> Hashable:
        return (event.node_a, event.node_b)

    def fault_event(self, route: Route, msg: Any, t: float) -> Event:
        return range_to_event(
            msg, route.robot, route.robot_b, node_a=route.node_a, node_b=route.node_b, t=t
        )

    def write_back(self, msg: Any, before: Any, after: Any) -> Any:
        return (
            dataclasses.replace(msg, range=after.distance)
            if after.distance != before.distance
            else msg
        )

    def bag_check(
        self, config: TeamConfig, bag_topics: Iterable[str], resolved: Iterable[Route]
    ) -> tuple[list[str], list[str]]:
        """The bag's UWB topics involving a node no robot of the team carries (static anchors:
        not read, the method is infrastructure-free), and a warning if no pair has a topic."""
        template = config.uwb.range_topic
        read = {r.topic for r in resolved}
        listed = [] if config.uwb.peer_field else match_range_topics(bag_topics, template)
        ignored = [t for t in listed if t not in read]
        nodes = [n for r in config.robots for n in r.nodes]
        warnings = []
        if len(nodes) >= 2 and not read:
            warnings.append(
                f"no UWB range topic between the team's nodes {nodes} (template {template!r}): no ranges"
            )
        return ignored, warnings


def _check_range_template(template: str, peers: bool = False) -> None:
    """A pair's topic names both nodes; a node's topic (a type listing peers) its node or robot."""
    if peers:
        if ("{a}" in template) == ("{robot}" in template) or "{b}" in template:
            raise ConfigError(
                f"uwb.range_topic {template!r}: with uwb.peer_field each node publishes its own topic: "
                "use {a} (its node id) or {robot} (its robot), not {b}"
            )
    elif "{a}" not in template or "{b}" not in template:
        raise ConfigError(f"uwb.range_topic {template!r} must contain both {{a}} and {{b}}")


def match_range_topics(topics: Iterable[str], template: str) -> dict[str, tuple[str, str]]:
    """The topics matching a UWB range-topic template, any nodes (static anchors too):
    topic -> (node a, node b), sorted by topic.

    Raises :class:`~relloc.config.ConfigError` for a template without ``{a}`` and ``{b}``.
    """
    _check_range_template(template)
    parts = re.split(r"(\{a\}|\{b\})", template)
    pattern = "".join(f"(?P<{p[1]}>[^/]+)" if p in ("{a}", "{b}") else re.escape(p) for p in parts)
    regex = re.compile(f"^{pattern}$")
    out: dict[str, tuple[str, str]] = {}
    for topic in sorted(topics):
        match = regex.match(topic)
        if match is not None:
            out[topic] = (match.group("a"), match.group("b"))
    return out


ODOMETRY_SENSOR = Odometry()
SIGHTING = Sighting()
GROUND_TRUTH = GroundTruth()
DETECTION = Detection()
RANGE_SENSOR = Range()
