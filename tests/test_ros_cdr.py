"""The fast CDR codecs agree with ``rosbags`` on every message and defer on anything odd."""

from __future__ import annotations

import math

import numpy as np
import pytest

from relloc.events import OdometryEvent, RangeEvent
from relloc.ros import cdr as ros_cdr
from relloc.ros import messages as rm


def _types():
    return rm.typestore().types


def _odometry(rng: np.random.Generator, frame: str, child: str):
    """An Odometry with every field random (covariances too), so an offset error shows."""
    t = _types()
    vec = t["geometry_msgs/msg/Vector3"]
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](*rng.normal(size=3)),
        orientation=t["geometry_msgs/msg/Quaternion"](*q),
    )
    twist = t[rm.TWIST](linear=vec(*rng.normal(size=3)), angular=vec(*rng.normal(size=3)))
    return t[rm.ODOMETRY](
        header=t["std_msgs/msg/Header"](stamp=rm.time_msg(rng.uniform(0, 2e9)), frame_id=frame),
        child_frame_id=child,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=rng.normal(size=36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=twist, covariance=rng.normal(size=36)
        ),
    )


def _range(rng: np.random.Generator, frame: str, distro: str):
    """A Range of ``distro``'s layout (since Iron with a variance) with every field random."""
    types = rm.typestore(distro).types
    extra = {"variance": float(rng.normal())} if distro != "humble" else {}
    return types[rm.RANGE](
        header=types["std_msgs/msg/Header"](stamp=rm.time_msg(rng.uniform(0, 2e9)), frame_id=frame),
        radiation_type=int(rng.integers(0, 3)),
        field_of_view=float(rng.normal()),
        min_range=float(rng.normal()),
        max_range=float(rng.normal()),
        range=float(rng.normal()),
        **extra,
    )


def _serialize(msg, little_endian: bool, distro: str = "jazzy") -> bytes:
    store = rm.typestore(distro)
    return bytes(store.serialize_cdr(msg, msg.__msgtype__, little_endian=little_endian))


# Frame ids of every length modulo 8 exercise every alignment of what follows them.
FRAMES = ["", "a", "ab", "odom", "tb1/odom", "base_link", "ünïcode", "x" * 13]


@pytest.mark.parametrize("little_endian", [True, False])
def test_odometry_fields_match_rosbags(little_endian: bool) -> None:
    rng = np.random.default_rng(0)
    for frame in FRAMES:
        for child in FRAMES:
            raw = _serialize(_odometry(rng, frame, child), little_endian)
            got = ros_cdr.decode_odometry(raw)
            assert got is not None
            ev = rm.odometry_to_event(rm.decode(raw, rm.ODOMETRY), "r")
            want = (rm.stamp_to_sec(rm.decode(raw, rm.ODOMETRY).header.stamp),
                    ev.x, ev.y, ev.yaw, ev.v, ev.w, ev.z)  # fmt: skip
            assert got == pytest.approx(want, rel=0, abs=1e-12)


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
@pytest.mark.parametrize("little_endian", [True, False])
def test_range_fields_match_rosbags(little_endian: bool, distro: str) -> None:
    """Both layouts of Range (Humble's, and Iron's on with a variance) are read, each by its
    own size; the other layout's size is refused."""
    rng = np.random.default_rng(1)
    for frame in FRAMES:
        raw = _serialize(_range(rng, frame, distro), little_endian, distro)
        msg = rm.decode(raw, rm.RANGE)
        want = (rm.stamp_to_sec(msg.header.stamp), msg.range)
        assert ros_cdr.decode_range(raw) == want
        assert ros_cdr.decode_range(raw, distro != "humble") == want
        assert ros_cdr.decode_range(raw, distro == "humble") is None


def test_nan_range_is_passed_through_for_the_caller_to_reject() -> None:
    raw = rm.encode(rm.range_msg(RangeEvent(t=1.0, robot_a="a", robot_b="b", distance=math.nan)))
    stamp, value = ros_cdr.decode_range(raw)
    assert stamp == 1.0 and math.isnan(value)
    assert rm.range_rejection(value) == "nonfinite"


def _malformed(raw: bytes, rng: np.random.Generator) -> list[bytes]:
    out = [raw[:n] for n in range(len(raw))]  # every truncation
    out += [raw + b"\x00", raw + bytes(8), b"\x07\x07\x00\x00" + raw[4:], b"\x01" + raw[1:]]
    out += [raw[:8] + b"\xff\xff\xff\x7f" + raw[12:]]  # absurd frame_id length
    out += [raw[:12] + b"\x02\x00\x00\x00" + raw[16:]]  # frame_id length off by one
    for _ in range(200):  # random byte flips
        b = bytearray(raw)
        b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
        out.append(bytes(b))
    return out


@pytest.mark.parametrize(
    ("msgtype", "fast", "distro"),
    [
        (rm.ODOMETRY, ros_cdr.decode_odometry, "jazzy"),
        (rm.RANGE, lambda raw: ros_cdr.decode_range(raw, True), "jazzy"),
        (rm.RANGE, lambda raw: ros_cdr.decode_range(raw, False), "humble"),
    ],
)
def test_malformed_payloads_defer_to_the_full_decoder(msgtype: str, fast, distro: str) -> None:
    """Whenever the fast path of a layout answers, rosbags decodes the same bytes to the same
    values; a truncated, padded or re-headed payload is never answered by the fast path."""
    rng = np.random.default_rng(2)
    odom = OdometryEvent(t=5.5, robot="a", x=1.0, y=2.0, yaw=0.3, v=0.1, w=0.2)
    rng_ev = RangeEvent(t=5.5, robot_a="a", robot_b="b", distance=3.0)
    msg = rm.odometry_msg(odom) if msgtype == rm.ODOMETRY else rm.range_msg(rng_ev, distro=distro)
    raw = rm.encode(msg)
    answered = 0
    for payload in _malformed(raw, rng):
        got = fast(payload)
        if len(payload) != len(raw) or payload[:2] != raw[:2]:
            assert got is None, payload
        if got is None:
            continue
        answered += 1
        full = rm.decode(payload, msgtype)  # must not raise
        if msgtype == rm.RANGE:
            assert got == (rm.stamp_to_sec(full.header.stamp), full.range)
        else:
            ev = rm.odometry_to_event(full, "a")
            np.testing.assert_equal(got[1:], (ev.x, ev.y, ev.yaw, ev.v, ev.w, ev.z))
    assert answered > 0  # flips in the float fields are still valid messages


@pytest.mark.parametrize("frame", FRAMES)
@pytest.mark.parametrize("t", [0.0, 9.5, 1665495600.123456789, 3.9999999999])
def test_pose_encoder_is_byte_identical_to_rosbags(frame: str, t: float) -> None:
    cov = np.arange(36, dtype=float).reshape(6, 6) / 7.0
    want = rm.encode(rm.pose_with_covariance_msg(t, 1.5, -0.5, yaw=0.3, frame_id=frame))
    got = ros_cdr.encode_pose_with_covariance_stamped(t, 1.5, -0.5, 0.3, [0.0] * 36, frame)
    assert got == want
    msg = rm.decode(
        ros_cdr.encode_pose_with_covariance_stamped(t, 1.0, 2.0, -2.0, cov.ravel().tolist(), frame),
        rm.POSE_WITH_COVARIANCE_STAMPED,
    )
    np.testing.assert_array_equal(np.asarray(msg.pose.covariance).reshape(6, 6), cov)
    assert rm.yaw_from_quaternion(msg.pose.pose.orientation) == pytest.approx(-2.0)
    assert msg.header.frame_id == frame
    with pytest.raises(ValueError, match="36 values"):
        ros_cdr.encode_pose_with_covariance_stamped(t, 0.0, 0.0, 0.0, [0.0] * 9, frame)
