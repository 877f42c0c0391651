"""ROS 2 message handling: CDR round trips, malformed payloads, frames and converters."""

from __future__ import annotations

import math

import numpy as np
import pytest

from relloc.config import CameraConfig
from relloc.events import OdometryEvent, RangeEvent
from relloc.ros import messages as rm
from relloc.ros.estimate_msgs import NOT_ESTIMATED


def _types():
    return rm.typestore().types


def _header(t: float, frame: str = "f"):
    return _types()["std_msgs/msg/Header"](stamp=rm.time_msg(t), frame_id=frame)


def _point(x: float, y: float, z: float):
    return _types()["geometry_msgs/msg/Point"](x=x, y=y, z=z)


def _pose(x: float, y: float, z: float, yaw: float = 0.0):
    return _types()["geometry_msgs/msg/Pose"](
        position=_point(x, y, z), orientation=rm.quaternion_from_yaw(yaw)
    )


def _spatial_detection(label_scores: list[tuple[str, float]], pos: tuple[float, float, float]):
    t = _types()
    hyps = [t["vision_msgs/msg/ObjectHypothesis"](id=lab, score=s) for lab, s in label_scores]
    bbox = t["vision_msgs/msg/BoundingBox2D"](
        center=t["geometry_msgs/msg/Pose2D"](x=100.0, y=50.0, theta=0.0), size_x=20.0, size_y=30.0
    )
    return t["depthai_ros_msgs/msg/SpatialDetection"](
        results=hyps, bbox=bbox, position=_point(*pos), is_tracking=False, tracking_id=""
    )


def _detection_array(t: float, dets: list) -> object:
    return _types()[rm.SPATIAL_DETECTION_ARRAY](
        header=_header(t, "oak_rgb_camera_optical_frame"), detections=dets
    )


def sample_messages() -> dict[str, object]:
    """One message of every kind relloc reads or writes."""
    types = _types()
    odom = rm.odometry_msg(OdometryEvent(t=12.25, robot="a", x=1.0, y=-2.0, yaw=0.7, v=0.2, w=-0.1))
    rng = rm.range_msg(RangeEvent(t=3.5, robot_a="a", robot_b="b", distance=2.75))
    pose = types[rm.POSE_STAMPED](header=_header(7.0, "world"), pose=_pose(1.0, 2.0, 0.1, 1.2))
    pose_array = types[rm.POSE_ARRAY](
        header=_header(8.0, ""), poses=[_pose(0.1, -0.2, 3.0), _pose(0.0, 0.0, 0.0)]
    )
    pwc = rm.pose_with_covariance_msg(9.5, 1.5, -0.5, yaw=0.3, cov=np.diag([0.04, 0.09, 0.01]))
    twist = rm.twist_msg(0.3, -0.4)
    dets = _detection_array(
        10.0,
        [
            _spatial_detection([("56", 0.7), ("0", 0.2)], (0.5, -0.1, 3.0)),
            _spatial_detection([("0", 0.9)], (0.0, 0.0, 0.0)),
        ],
    )
    return {
        rm.ODOMETRY: odom,
        rm.RANGE: rng,
        rm.POSE_STAMPED: pose,
        rm.POSE_ARRAY: pose_array,
        rm.POSE_WITH_COVARIANCE_STAMPED: pwc,
        rm.TWIST: twist,
        rm.SPATIAL_DETECTION_ARRAY: dets,
    }


# ---------------------------------------------------------------------------- CDR
@pytest.mark.parametrize("msgtype", list(sample_messages()))
def test_round_trip_is_byte_exact(msgtype: str) -> None:
    msg = sample_messages()[msgtype]
    raw = rm.encode(msg, msgtype)
    again = rm.decode(raw, msgtype)
    assert rm.encode(again, msgtype) == raw
    assert again.__msgtype__ == msgtype


def test_custom_types_are_registered_from_shipped_msg_files() -> None:
    names = set(rm.custom_types())
    assert {
        "vision_msgs/msg/ObjectHypothesis",
        "vision_msgs/msg/BoundingBox2D",
        "depthai_ros_msgs/msg/SpatialDetection",
        rm.SPATIAL_DETECTION_ARRAY,
    } <= names
    assert rm.typestore() is rm.typestore()  # built once


def test_header_stamp_read_without_decoding() -> None:
    for msgtype, msg in sample_messages().items():
        if msgtype == rm.TWIST:
            continue
        raw = rm.encode(msg, msgtype)
        assert rm.header_stamp_from_cdr(raw) == pytest.approx(rm.stamp_to_sec(msg.header.stamp))
    big_endian = rm.typestore().serialize_cdr(
        sample_messages()[rm.RANGE], rm.RANGE, little_endian=False
    )
    assert rm.header_stamp_from_cdr(bytes(big_endian)) == pytest.approx(3.5)
    with pytest.raises(rm.MessageDecodeError):
        rm.header_stamp_from_cdr(b"\x00\x01\x00")


@pytest.mark.parametrize("msgtype", list(sample_messages()))
def test_malformed_payloads_raise_one_clear_error(msgtype: str) -> None:
    raw = rm.encode(sample_messages()[msgtype], msgtype)
    rng = np.random.default_rng(0)
    bad = [
        b"",
        b"\x00\x01",
        b"\x07\x07\x00\x00" + raw[4:],  # unknown encapsulation
        raw[: len(raw) // 2],
        raw[:-9] if len(raw) > 13 else raw[:4],
        raw + bytes(16),  # trailing garbage
        raw[:4] + bytes(rng.integers(0, 256, size=len(raw) - 4, dtype=np.uint8)) + b"\xff" * 9,
        raw[:4] + b"\xff\xff\xff\x7f" * 8,  # absurd string/sequence lengths
    ]
    for payload in bad:
        with pytest.raises(rm.MessageDecodeError, match=msgtype) as info:
            rm.decode(payload, msgtype)
        assert isinstance(info.value, ValueError)


def test_truncation_at_every_length_is_a_decode_error() -> None:
    msgtype = rm.SPATIAL_DETECTION_ARRAY
    raw = rm.encode(sample_messages()[msgtype], msgtype)
    for n in range(len(raw) - 8):
        with pytest.raises(rm.MessageDecodeError):
            rm.decode(raw[:n], msgtype)


def test_unknown_type_is_a_decode_error() -> None:
    with pytest.raises(rm.MessageDecodeError, match="unknown message type"):
        rm.decode(b"\x00\x01\x00\x00", "no_pkg/msg/Nothing")


# ---------------------------------------------------------------------------- helpers
def test_time_msg_carries_rounded_nanoseconds() -> None:
    t = rm.time_msg(1.9999999999)
    assert (t.sec, t.nanosec) == (2, 0)
    t = rm.time_msg(1665477211.25)
    assert (t.sec, t.nanosec) == (1665477211, 250_000_000)
    assert rm.stamp_to_sec(rm.time_msg(-0.5)) == pytest.approx(-0.5)


@pytest.mark.parametrize("yaw", [0.0, 0.3, -2.0, math.pi - 1e-9, 3.0])
def test_yaw_quaternion_round_trip(yaw: float) -> None:
    assert rm.yaw_from_quaternion(rm.quaternion_from_yaw(yaw)) == pytest.approx(yaw)


def test_yaw_ignores_small_roll_and_pitch() -> None:
    # yaw 0.8 composed with roll 0.05 and pitch -0.04 (z-y-x Euler)
    r, p, y = 0.05, -0.04, 0.8
    cr, sr, cp, sp, cy, sy = (
        math.cos(r / 2),
        math.sin(r / 2),
        math.cos(p / 2),
        math.sin(p / 2),
        math.cos(y / 2),
        math.sin(y / 2),
    )
    q = _types()["geometry_msgs/msg/Quaternion"](
        x=sr * cp * cy - cr * sp * sy,
        y=cr * sp * cy + sr * cp * sy,
        z=cr * cp * sy - sr * sp * cy,
        w=cr * cp * cy + sr * sp * sy,
    )
    assert rm.yaw_from_quaternion(q) == pytest.approx(0.8, abs=1e-9)


# ---------------------------------------------------------------------------- frames
def test_optical_axes_map_to_body_axes() -> None:
    cam = CameraConfig()
    out = rm.camera_to_body([[0, 0, 1], [1, 0, 0], [0, 1, 0]], cam)
    np.testing.assert_allclose(out, [[1, 0, 0], [0, -1, 0], [0, 0, -1]], atol=1e-12)


def test_camera_extrinsics_yaw_pitch_and_offset() -> None:
    forward = [[0.0, 0.0, 2.0]]
    left = rm.camera_to_body(forward, CameraConfig(yaw_deg=90.0))
    np.testing.assert_allclose(left, [[0.0, 2.0, 0.0]], atol=1e-12)
    down = rm.camera_to_body(forward, CameraConfig(pitch_deg=30.0))
    np.testing.assert_allclose(down, [[2 * math.cos(math.radians(30)), 0.0, -1.0]], atol=1e-12)
    moved = rm.camera_to_body(forward, CameraConfig(x=-0.06, y=0.01, z=0.24))
    np.testing.assert_allclose(moved, [[1.94, 0.01, 0.24]], atol=1e-12)


# ---------------------------------------------------------------------------- converters
def test_odometry_to_event_reads_pose_and_twist() -> None:
    ev = OdometryEvent(t=12.25, robot="a", x=1.0, y=-2.0, yaw=0.7, v=0.2, w=-0.1)
    msg = rm.decode(rm.encode(rm.odometry_msg(ev)), rm.ODOMETRY)
    assert msg.header.frame_id == "odom" and msg.child_frame_id == "base_link"
    back = rm.odometry_to_event(msg, "a")
    assert back.t == pytest.approx(ev.t)
    for field in ("x", "y", "yaw", "v", "w"):
        assert getattr(back, field) == pytest.approx(getattr(ev, field))
    assert rm.odometry_to_event(msg, "a", t=99.0).t == 99.0


def test_range_to_event_keeps_nodes_and_value() -> None:
    msg = rm.decode(rm.encode(sample_messages()[rm.RANGE]), rm.RANGE)
    ev = rm.range_to_event(msg, "turtle01", "turtle03", node_a="n_7", node_b="n_3")
    assert ev.distance == pytest.approx(2.75)
    assert ev.t == pytest.approx(3.5)
    assert ev.node_pair == "n_3-n_7"
    assert rm.range_rejection(float("nan")) == "nonfinite"
    assert rm.range_rejection(-0.1) == "nonpositive"
    assert rm.range_rejection(0.0) == "nonpositive"
    assert rm.range_rejection(3.0) is None


def test_pose_to_ground_truth() -> None:
    msg = sample_messages()[rm.POSE_STAMPED]
    gt = rm.pose_to_ground_truth(msg, "turtle01")
    assert (gt.t, gt.robot, gt.position) == (7.0, "turtle01", (1.0, 2.0))
    assert gt.yaw == pytest.approx(1.2)


def test_depthai_detections_to_body_frame_and_rejections() -> None:
    t = _types()
    nan_det = _spatial_detection([("56", 0.5)], (float("nan"), 0.0, 2.0))
    behind = _spatial_detection([("56", 0.5)], (0.1, 0.0, -1.0))
    no_label = _spatial_detection([], (0.0, 0.2, 1.5))
    msg = sample_messages()[rm.SPATIAL_DETECTION_ARRAY]
    msg = t[rm.SPATIAL_DETECTION_ARRAY](
        header=msg.header, detections=[*msg.detections, nan_det, behind, no_label]
    )
    msg = rm.decode(rm.encode(msg), rm.SPATIAL_DETECTION_ARRAY)
    cam = CameraConfig(x=-0.06, z=0.24)
    ev, rejected = rm.detections_to_event(msg, "turtle05", cam)
    assert ev.t == pytest.approx(10.0) and ev.robot == "turtle05"
    assert rejected == {"zero_position": 1, "nonfinite": 1, "behind_camera": 1}
    chair, unlabelled = ev.objects
    assert (chair.label, chair.score) == ("56", pytest.approx(0.7))  # best hypothesis
    assert (chair.x, chair.y, chair.z) == pytest.approx((2.94, -0.5, 0.34))
    assert (unlabelled.label, unlabelled.score) == ("", 1.0)


def test_posearray_detections() -> None:
    msg = rm.decode(rm.encode(sample_messages()[rm.POSE_ARRAY]), rm.POSE_ARRAY)
    ev, rejected = rm.detections_to_event(msg, "turtle01", CameraConfig())
    assert rejected == {"zero_position": 1}
    (obj,) = ev.objects
    assert obj.label == "" and (obj.x, obj.y, obj.z) == pytest.approx((3.0, -0.1, 0.2))
    with pytest.raises(TypeError):
        rm.detections_to_event(sample_messages()[rm.TWIST], "turtle01", CameraConfig())


# ---------------------------------------------------------------------------- builders
def test_pose_with_covariance_layout() -> None:
    cov3 = [[0.04, 0.01, 0.002], [0.01, 0.09, 0.003], [0.002, 0.003, 0.01]]
    msg = rm.decode(
        rm.encode(rm.pose_with_covariance_msg(9.5, 1.5, -0.5, yaw=0.3, cov=cov3, frame_id="ref")),
        rm.POSE_WITH_COVARIANCE_STAMPED,
    )
    full = np.asarray(msg.pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(full[np.ix_([0, 1, 5], [0, 1, 5])], cov3)
    np.testing.assert_array_equal(np.diag(full)[2:5], [NOT_ESTIMATED] * 3)
    assert full[2:5, [0, 1, 5]].sum() == full[[0, 1, 5]][:, 2:5].sum() == 0.0
    assert msg.header.frame_id == "ref"
    assert rm.yaw_from_quaternion(msg.pose.pose.orientation) == pytest.approx(0.3)
    cov2 = rm.pose_with_covariance_msg(0.0, 0.0, 0.0, cov=np.eye(2)).pose.covariance
    assert cov2[0] == cov2[7] == 1.0 and cov2[35] == NOT_ESTIMATED
    with pytest.raises(ValueError, match="2x2 or 3x3"):
        rm.pose_with_covariance_msg(0.0, 0.0, 0.0, cov=np.eye(4))


def test_twist_and_range_builders() -> None:
    twist = rm.decode(rm.encode(rm.twist_msg(0.3, -0.4)), rm.TWIST)
    assert (twist.linear.x, twist.angular.z) == pytest.approx((0.3, -0.4))
    assert twist.linear.y == twist.angular.x == 0.0
    ev = RangeEvent(t=1.0, robot_a="a", robot_b="b", distance=4.5, node_a="n_3", node_b="n_7")
    msg = rm.decode(rm.encode(rm.range_msg(ev, frame_id="n_3")), rm.RANGE)
    back = rm.range_to_event(msg, "a", "b", node_a="n_3", node_b="n_7")
    assert back == ev
