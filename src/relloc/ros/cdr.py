"""Fast CDR codecs for the live engine's hot messages, checked against ``rosbags``.

The live engine decodes every odometry and UWB message a team publishes (about 200 per second
for five robots) and encodes one pose per robot and estimate. ``rosbags``' generated
(de)serialisers build a Python object per nested message (header, stamp, pose, point, a NumPy
covariance...); in a process that sleeps between messages that costs 100-200 us a message,
most of the engine's CPU. These functions read and write the few fields relloc needs straight
from the bytes with precompiled :mod:`struct` layouts.

They are a fast path, not a second implementation of CDR: the decoders return ``None`` for
anything that is not exactly a well-formed message of their type in the plain layout (XCDR1,
either endianness, no trailing bytes, NUL-terminated UTF-8 strings), and the caller then falls
back to :func:`relloc.ros.messages.decode`, which decodes it or raises a clear
:class:`~relloc.ros.messages.MessageDecodeError`. ``tests/test_ros_cdr.py`` checks them against
``rosbags`` on random messages and on every kind of malformed payload.

CDR alignment is relative to the end of the 4-byte encapsulation header.
"""

from __future__ import annotations

import math
import struct

__all__ = [
    "decode_odometry",
    "decode_range",
    "encode_pose_with_covariance_stamped",
    "split_stamp",
    "yaw_from_xyzw",
]

_ENCAPSULATION = {b"\x00\x01": "<", b"\x00\x00": ">"}  # CDR_LE, CDR_BE

_U32 = {e: struct.Struct(e + "I") for e in "<>"}
_STAMP = {e: struct.Struct(e + "iI") for e in "<>"}
# nav_msgs/Odometry after the two strings: pose (position 3, orientation 4), its covariance 36,
# twist (linear 3, angular 3), its covariance 36; all float64.
_ODOM_BODY = {e: struct.Struct(e + "85d") for e in "<>"}
# sensor_msgs/Range after the header: radiation_type (uint8), then, aligned to 4,
# field_of_view, min_range, max_range, range (float32), and since Iron variance (float32).
_RANGE_FLOATS = {e: struct.Struct(e + "4f") for e in "<>"}
_RANGE_SIZES: dict[bool | None, int] = {False: 16, True: 20}


def split_stamp(t: float) -> tuple[int, int]:
    """Float seconds as a ROS ``(sec, nanosec)`` stamp: nanoseconds rounded, carried."""
    sec = math.floor(t)
    nanosec = round((t - sec) * 1e9)
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return int(sec), int(nanosec)


def yaw_from_xyzw(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rad, z-y-x Euler convention) of the quaternion ``(x, y, z, w)``: small roll and
    pitch of a robot on uneven floor do not leak into it."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _string_end(raw: bytes, pos: int, endian: str) -> int | None:
    """Offset just after a CDR string starting at ``pos`` (aligned), or ``None`` if invalid."""
    pos += -(pos - 4) % 4
    if pos + 4 > len(raw):
        return None
    (n,) = _U32[endian].unpack_from(raw, pos)
    end = pos + 4 + n
    if n == 0 or end > len(raw) or raw[end - 1] != 0:
        return None
    try:
        raw[pos + 4 : end - 1].decode()
    except UnicodeDecodeError:
        return None
    return end


def _header(raw: bytes) -> tuple[str, float, int] | None:
    """``(endianness, stamp in s, offset after the header)`` of a message led by a Header."""
    endian = _ENCAPSULATION.get(raw[:2])
    if endian is None or len(raw) < 12:
        return None
    sec, nanosec = _STAMP[endian].unpack_from(raw, 4)
    end = _string_end(raw, 12, endian)
    if end is None:
        return None
    return endian, sec + nanosec * 1e-9, end


def decode_odometry(
    raw: bytes,
) -> tuple[float, float, float, float, float, float, float] | None:
    """``nav_msgs/Odometry`` -> ``(stamp, x, y, yaw, v, w, z)``, or ``None`` (use the full decoder).

    ``yaw`` is :func:`relloc.ros.messages.yaw_from_quaternion` of the orientation; ``v`` and
    ``w`` are ``twist.linear.x`` and ``twist.angular.z``.
    """
    head = _header(raw)
    if head is None:
        return None
    endian, stamp, start = head
    pos = _string_end(raw, start, endian)  # child_frame_id
    if pos is None:
        return None
    pos += -(pos - 4) % 8
    body = _ODOM_BODY[endian]
    if pos + body.size != len(raw):
        return None
    f = body.unpack_from(raw, pos)
    return stamp, f[0], f[1], yaw_from_xyzw(*f[3:7]), f[43], f[48], f[2]


def decode_range(raw: bytes, variance: bool | None = None) -> tuple[float, float] | None:
    """``sensor_msgs/Range`` -> ``(stamp, range)``, or ``None`` (use the full decoder).

    ``variance``: the layout since Iron (``True``), Humble's (``False``) or either (``None``;
    their sizes differ by the one float).
    """
    head = _header(raw)
    if head is None:
        return None
    endian, stamp, pos = head
    pos += 1  # radiation_type
    pos += -(pos - 4) % 4
    rest = len(raw) - pos
    if rest != _RANGE_SIZES.get(variance, rest) or rest not in (16, 20):
        return None
    return stamp, _RANGE_FLOATS[endian].unpack_from(raw, pos)[3]


def encode_pose_with_covariance_stamped(
    t: float,
    x: float,
    y: float,
    yaw: float,
    covariance: list[float],
    frame_id: str,
    z: float = 0.0,
) -> bytes:
    """``geometry_msgs/PoseWithCovarianceStamped`` as little-endian CDR.

    ``covariance`` is the row-major 6x6 (36 values); the stamp is :func:`split_stamp` of ``t``.
    """
    if len(covariance) != 36:
        raise ValueError(f"covariance needs 36 values, got {len(covariance)}")
    sec, nanosec = split_stamp(t)
    name = frame_id.encode() + b"\x00"
    head = b"\x00\x01\x00\x00" + struct.pack("<iII", sec, nanosec, len(name)) + name
    head += bytes(-(len(head) - 4) % 8)
    half = yaw / 2.0
    pose = struct.pack("<7d", x, y, z, 0.0, 0.0, math.sin(half), math.cos(half))
    return head + pose + struct.pack("<36d", *covariance)
