"""ROS 2 messages without ROS: the type store, CDR (de)serialisation and event converters.

Every way relloc talks to robots carries ROS 2 messages serialised as CDR: rosbag2 files store
them, and a Zenoh bridge (zenoh-bridge-ros2dds, rmw_zenoh) forwards the very same bytes. This
module is the one place that knows the message layouts, so the rosbag source, the live Zenoh
engine and the simulator that publishes over Zenoh all share it. It has three parts:

* **Type store.** :func:`typestore` is a distribution's ``rosbags`` store
  (:mod:`relloc.ros.stores`) plus the custom detection types of the TIERS robots
  (``depthai_ros_msgs/msg/SpatialDetectionArray`` and the ``vision_msgs`` types it uses),
  parsed from the ``.msg`` files shipped in ``relloc/ros/msg``.
* **CDR.** :func:`decode` / :func:`encode` (:mod:`relloc.ros.codec`, re-exported here) wrap
  ``deserialize_cdr`` / ``serialize_cdr`` in every layout of a type. A malformed payload
  raises :class:`MessageDecodeError` (a ``ValueError``) with the type name and the reason,
  never an ``IndexError`` from deep inside the deserialiser: a live engine must be able to drop
  one bad packet and go on.
* **Converters.** Pure functions from decoded messages to :mod:`relloc.events` (odometry, UWB
  ranges, motion-capture poses, spatial detections) and builders from relloc values to messages
  (estimate -> ``PoseWithCovarianceStamped``, ``(v, w)`` -> ``Twist``, odometry/range events ->
  ``Odometry``/``Range``) for publishing.

Frames of the detections: the OAK-D reports object positions in the camera *optical* frame (x
right, y down, z forward). :func:`camera_to_body` turns them into the robot body frame (x
forward, y left, z up) with the robot's :class:`~relloc.config.CameraConfig`: first the fixed
axis permutation optical -> camera link, then the camera's pitch (down positive) and yaw (left
positive), then its position on the robot.
"""

from __future__ import annotations

import math
import struct
from collections import Counter
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from relloc.config import CameraConfig
from relloc.events import (
    DetectionEvent,
    GroundTruthEvent,
    ObjectDetection,
    OdometryEvent,
    RangeEvent,
    SightingEvent,
)
from relloc.ros.cdr import split_stamp, yaw_from_xyzw
from relloc.ros.codec import decode, encode, in_distro, in_layout, typestore, zero_message
from relloc.ros.estimate_msgs import pose_covariance
from relloc.ros.stores import (
    DEFAULT_DISTRO,
    MSG_DIR,
    MessageDecodeError,
    custom_types,
    register_types,
)

__all__ = [
    "MOCAP_TYPES",
    "MSG_DIR",
    "ODOMETRY",
    "POINT_STAMPED",
    "POSE_ARRAY",
    "POSE_STAMPED",
    "POSE_WITH_COVARIANCE_STAMPED",
    "RANGE",
    "SPATIAL_DETECTION_ARRAY",
    "TRANSFORM_STAMPED",
    "TWIST",
    "MessageDecodeError",
    "camera_to_body",
    "custom_types",
    "decode",
    "detection_rejection",
    "detections_to_event",
    "encode",
    "header_stamp_from_cdr",
    "in_distro",
    "in_layout",
    "odometry_msg",
    "odometry_to_event",
    "point_to_sighting",
    "pose_stamped_msg",
    "pose_to_ground_truth",
    "pose_with_covariance_msg",
    "quaternion_from_yaw",
    "range_msg",
    "range_rejection",
    "range_to_event",
    "register_types",
    "sighting_msg",
    "stamp_to_sec",
    "time_msg",
    "twist_msg",
    "typestore",
    "yaw_from_quaternion",
    "zero_message",
]

ODOMETRY = "nav_msgs/msg/Odometry"
RANGE = "sensor_msgs/msg/Range"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TWIST = "geometry_msgs/msg/Twist"
SPATIAL_DETECTION_ARRAY = "depthai_ros_msgs/msg/SpatialDetectionArray"
MOCAP_TYPES = (POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, TRANSFORM_STAMPED, ODOMETRY)
"""The message types motion capture comes in (:func:`pose_to_ground_truth` reads each)."""


def header_stamp_from_cdr(raw: bytes | memoryview) -> float:
    """Header stamp (s) of a CDR message whose first field is a ``std_msgs/Header``.

    Reads only the first 12 bytes, so a reader can look at the clocks of thousands of messages
    without decoding them. Raises :class:`MessageDecodeError` if the payload is too short.
    """
    if len(raw) < 12 or bytes(raw[:1]) != b"\x00" or bytes(raw[1:2]) not in (b"\x00", b"\x01"):
        raise MessageDecodeError(f"not a CDR message with a header ({len(raw)} bytes)")
    fmt = "<iI" if bytes(raw[1:2]) == b"\x01" else ">iI"
    sec, nanosec = struct.unpack_from(fmt, raw, 4)
    return sec + nanosec * 1e-9


# ---------------------------------------------------------------------------- small helpers
def stamp_to_sec(stamp: Any) -> float:
    """A ``builtin_interfaces/Time`` as float seconds."""
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def time_msg(t: float) -> Any:
    """Float seconds as a ``builtin_interfaces/msg/Time`` (nanoseconds rounded, carried)."""
    sec, nanosec = split_stamp(t)
    return typestore().types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _header(t: float, frame_id: str) -> Any:
    return typestore().types["std_msgs/msg/Header"](stamp=time_msg(t), frame_id=frame_id)


def yaw_from_quaternion(q: Any) -> float:
    """Yaw (rotation about z, rad, in ``(-pi, pi]``) of a ``geometry_msgs/Quaternion``.

    Uses the z-y-x Euler convention, so small roll/pitch of a robot on uneven floor does not
    leak into the heading.
    """
    return yaw_from_xyzw(q.x, q.y, q.z, q.w)


def quaternion_from_yaw(yaw: float) -> Any:
    """A ``geometry_msgs/Quaternion`` for a pure rotation ``yaw`` about z."""
    return typestore().types["geometry_msgs/msg/Quaternion"](
        x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0)
    )


def _msg_time(msg: Any, t: float | None) -> float:
    return stamp_to_sec(msg.header.stamp) if t is None else float(t)


# ---------------------------------------------------------------------------- messages -> events
def odometry_to_event(msg: Any, robot: str, *, t: float | None = None) -> OdometryEvent:
    """``nav_msgs/Odometry`` -> :class:`OdometryEvent` (pose in the robot's odometry frame).

    ``t`` overrides the header stamp (used for topics recorded with zero stamps).
    """
    pose = msg.pose.pose
    twist = msg.twist.twist
    return OdometryEvent(
        t=_msg_time(msg, t),
        robot=robot,
        x=float(pose.position.x),
        y=float(pose.position.y),
        yaw=yaw_from_quaternion(pose.orientation),
        v=float(twist.linear.x),
        w=float(twist.angular.z),
        z=float(pose.position.z),
    )


def range_to_event(
    msg: Any,
    robot_a: str,
    robot_b: str,
    *,
    node_a: str = "",
    node_b: str = "",
    t: float | None = None,
) -> RangeEvent:
    """``sensor_msgs/Range`` -> :class:`RangeEvent`. The value is passed as is (NaN too):
    deciding what is valid is the caller's job (see :func:`range_rejection`)."""
    return RangeEvent(
        t=_msg_time(msg, t),
        robot_a=robot_a,
        robot_b=robot_b,
        distance=float(msg.range),
        node_a=node_a,
        node_b=node_b,
    )


def range_rejection(distance: float) -> str | None:
    """Why a range value is unusable (``"nonfinite"``, ``"nonpositive"``) or ``None`` if valid.

    Two transceivers can never be at distance zero; the DWM1001 reports 0 or negative values
    only on failed exchanges.
    """
    if not math.isfinite(distance):
        return "nonfinite"
    if distance <= 0.0:
        return "nonpositive"
    return None


def pose_to_ground_truth(msg: Any, robot: str, *, t: float | None = None) -> GroundTruthEvent:
    """Motion capture (z up) in one of :data:`MOCAP_TYPES` -> :class:`GroundTruthEvent`."""
    if hasattr(msg, "transform"):  # TransformStamped
        position, orientation = msg.transform.translation, msg.transform.rotation
    else:  # PoseStamped; PoseWithCovarianceStamped and Odometry nest a PoseWithCovariance
        pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
        position, orientation = pose.position, pose.orientation
    return GroundTruthEvent(
        t=_msg_time(msg, t),
        robot=robot,
        position=(float(position.x), float(position.y)),  # planar: the height is not kept
        yaw=yaw_from_quaternion(orientation),
    )


def _rotation_camera_to_body(camera: CameraConfig) -> np.ndarray:
    """3x3 rotation taking optical-frame vectors (x right, y down, z fwd) to the body frame."""
    # optical -> camera link (x forward, y left, z up): x_l = z_o, y_l = -x_o, z_l = -y_o
    optical_to_link = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pitch = math.radians(camera.pitch_deg)  # down positive = positive rotation about +y
    yaw = math.radians(camera.yaw_deg)  # left positive = positive rotation about +z
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    r_pitch = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    r_yaw = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return r_yaw @ r_pitch @ optical_to_link


def camera_to_body(
    points: np.ndarray | Sequence[Sequence[float]], camera: CameraConfig
) -> np.ndarray:
    """Transform points ``(N, 3)`` from the camera optical frame to the robot body frame."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    rot = _rotation_camera_to_body(camera)
    return pts @ rot.T + np.array([camera.x, camera.y, camera.z])


def detection_rejection(x: float, y: float, z: float) -> str | None:
    """Why an optical-frame detection position is unusable, or ``None`` if valid.

    ``"nonfinite"``: NaN/inf; ``"zero_position"``: exactly (0, 0, 0), which the OAK-D reports
    when the box had no depth; ``"behind_camera"``: depth ``z <= 0`` is physically impossible.
    """
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return "nonfinite"
    if x == 0.0 and y == 0.0 and z == 0.0:
        return "zero_position"
    if z <= 0.0:
        return "behind_camera"
    return None


def _best_hypothesis(results: Iterable[Any]) -> tuple[str, float]:
    best_label, best_score = "", -math.inf
    for hyp in results:
        score = float(hyp.score)
        if score > best_score:
            best_label, best_score = str(hyp.id), score
    return (best_label, best_score) if math.isfinite(best_score) else ("", 1.0)


def detections_to_event(
    msg: Any,
    robot: str,
    camera: CameraConfig,
    *,
    t: float | None = None,
) -> tuple[DetectionEvent, Counter[str]]:
    """Spatial detections -> (:class:`DetectionEvent` in the body frame, rejected counts).

    Accepts ``depthai_ros_msgs/SpatialDetectionArray`` (label = the id of the best-scoring
    hypothesis, a COCO class index as a string; ``"56"`` is a chair) and the unlabelled
    ``geometry_msgs/PoseArray`` of the 2022-09 recordings (label ``""``, score 1). Invalid
    positions (see :func:`detection_rejection`) are dropped and counted by reason in the
    returned counter; the event keeps the valid objects (possibly none).
    """
    rejected: Counter[str] = Counter()
    raw: list[tuple[str, float, float, float, float]] = []
    if hasattr(msg, "detections"):
        for det in msg.detections:
            label, score = _best_hypothesis(det.results)
            p = det.position
            raw.append((label, score, float(p.x), float(p.y), float(p.z)))
    elif hasattr(msg, "poses"):
        for pose in msg.poses:
            p = pose.position
            raw.append(("", 1.0, float(p.x), float(p.y), float(p.z)))
    else:
        raise TypeError(f"not a detection message: {getattr(msg, '__msgtype__', type(msg))}")

    kept: list[tuple[str, float, float, float, float]] = []
    for item in raw:
        reason = detection_rejection(*item[2:])
        if reason is None:
            kept.append(item)
        else:
            rejected[reason] += 1
    objects: tuple[ObjectDetection, ...] = ()
    if kept:
        body = camera_to_body([item[2:] for item in kept], camera)
        objects = tuple(
            ObjectDetection(
                label=item[0], x=float(b[0]), y=float(b[1]), z=float(b[2]), score=item[1]
            )
            for item, b in zip(kept, body, strict=True)
        )
    return DetectionEvent(t=_msg_time(msg, t), robot=robot, objects=objects), rejected


# ---------------------------------------------------------------------------- values -> messages
def twist_msg(v: float, w: float) -> Any:
    """A ``geometry_msgs/Twist`` commanding forward speed ``v`` (m/s) and yaw rate ``w`` (rad/s)."""
    types = typestore().types
    vec = types["geometry_msgs/msg/Vector3"]
    return types[TWIST](linear=vec(x=float(v), y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=float(w)))


def _pose(x: float, y: float, yaw: float, z: float = 0.0) -> Any:
    types = typestore().types
    point = types["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z))
    return types["geometry_msgs/msg/Pose"](position=point, orientation=quaternion_from_yaw(yaw))


def pose_with_covariance_msg(
    t: float,
    x: float,
    y: float,
    *,
    yaw: float = 0.0,
    cov: np.ndarray | Sequence[Sequence[float]] | None = None,
    frame_id: str = "",
) -> Any:
    """An estimate as ``geometry_msgs/PoseWithCovarianceStamped`` (e.g. a robot relative to the
    reference robot, in the shared heading frame named by ``frame_id``).

    ``cov`` is the 2x2 covariance of ``(x, y)`` or the 3x3 one of ``(x, y, yaw)``; it fills the
    matching entries of the row-major 6x6 ROS covariance (x, y, z, roll, pitch, yaw), the rest
    as :func:`~relloc.ros.estimate_msgs.pose_covariance` does (relloc's one convention: what is
    not given is not estimated). Without ``cov`` the 36 entries are zero. An
    :class:`~relloc.estimate.Estimate` goes out by :mod:`relloc.ros.estimate_msgs`.
    """
    full = np.zeros((6, 6))
    if cov is not None:
        c = np.asarray(cov, dtype=float)
        if c.shape == (2, 2):
            full = np.array(pose_covariance(c.tolist())).reshape(6, 6)
        elif c.shape == (3, 3):
            full = np.array(pose_covariance(c[:2, :2].tolist(), c[2, 2])).reshape(6, 6)
            full[:2, 5], full[5, :2] = c[:2, 2], c[2, :2]
        else:
            raise ValueError(f"cov must be 2x2 or 3x3, got shape {c.shape}")
    types = typestore().types
    pwc = types["geometry_msgs/msg/PoseWithCovariance"](
        pose=_pose(x, y, yaw), covariance=full.reshape(36).astype(np.float64)
    )
    return types[POSE_WITH_COVARIANCE_STAMPED](header=_header(t, frame_id), pose=pwc)


def odometry_msg(
    event: OdometryEvent, *, frame_id: str = "odom", child_frame_id: str = "base_link"
) -> Any:
    """An :class:`OdometryEvent` as ``nav_msgs/Odometry`` (covariances zero, like the recordings;
    the position's z the event's, 0 for a ground robot)."""
    types = typestore().types
    vec = types["geometry_msgs/msg/Vector3"]
    zero36 = np.zeros(36, dtype=np.float64)
    twist = types[TWIST](
        linear=vec(x=float(event.v), y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=float(event.w))
    )
    return types[ODOMETRY](
        header=_header(event.t, frame_id),
        child_frame_id=child_frame_id,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose(event.x, event.y, event.yaw, event.z), covariance=zero36
        ),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=zero36.copy()),
    )


def range_msg(event: RangeEvent, *, frame_id: str = "", distro: str = DEFAULT_DISTRO) -> Any:
    """A :class:`RangeEvent` as ``sensor_msgs/Range`` of ``distro``, laid out like the TIERS
    UWB driver's messages (radiation type 0, field of view and limits 0; ``range`` in metres;
    since Iron a ``variance`` of 0, "unknown")."""
    msg = typestore(distro).types[RANGE]
    extra = {"variance": 0.0} if "variance" in getattr(msg, "__dataclass_fields__", {}) else {}
    return msg(
        header=_header(event.t, frame_id),
        radiation_type=0,
        field_of_view=0.0,
        min_range=0.0,
        max_range=0.0,
        range=float(event.distance),
        **extra,
    )


def pose_stamped_msg(event: GroundTruthEvent, *, frame_id: str = "world") -> Any:
    """A :class:`GroundTruthEvent` as ``geometry_msgs/PoseStamped`` (what a motion-capture
    bridge publishes; the inverse of :func:`pose_to_ground_truth`)."""
    x, y, *z = event.position  # z where the position has a height
    return typestore().types[POSE_STAMPED](
        header=_header(event.t, frame_id), pose=_pose(x, y, event.yaw, *z)
    )


def point_to_sighting(
    msg: Any,
    observer: str,
    target: str,
    sigma_range: float,
    sigma_bearing: float,
    *,
    t: float | None = None,
) -> SightingEvent:
    """A ``geometry_msgs/PointStamped`` of ``target`` in ``observer``'s body frame (REP 103:
    x forward, y left, the point's z ignored) as a range-and-bearing sighting."""
    x, y = float(msg.point.x), float(msg.point.y)
    return SightingEvent(
        _msg_time(msg, t),
        observer,
        target,
        math.hypot(x, y),
        math.atan2(y, x),
        sigma_range,
        sigma_bearing,
        "ros",
    )


def sighting_msg(event: SightingEvent, *, frame_id: str = "") -> Any:
    """A range-and-bearing sighting as ``geometry_msgs/PointStamped`` in the observer's body
    frame (the inverse of :func:`point_to_sighting`)."""
    if event.range is None or event.bearing is None:
        raise ValueError("a PointStamped sighting needs both a range and a bearing")
    types = typestore().types
    point = types["geometry_msgs/msg/Point"](
        x=event.range * math.cos(event.bearing), y=event.range * math.sin(event.bearing), z=0.0
    )
    return types[POINT_STAMPED](header=_header(event.t, frame_id), point=point)
