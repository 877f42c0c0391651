"""One robot's entry of an :class:`~relloc.estimate.Estimate` as a ROS 2 pose message.

Every path that publishes an estimate (the Zenoh sink, the MCAP file of ``relloc run --mcap``
and ``relloc serve --record``) goes through :func:`estimate_pose`, so that a consumer sees the
same ``geometry_msgs/msg/PoseWithCovarianceStamped`` whichever way it came:

* **Header.** The stamp is the estimate's time (:func:`~relloc.ros.cdr.split_stamp`:
  nanoseconds rounded, carried), ``frame_id`` the published estimate's
  (:attr:`Estimate.frame_id <relloc.estimate.Estimate.frame_id>`: ``<reference>`` for the
  heading frame, ``<reference>/base_link`` for the reference's body frame,
  ``<reference>/formation`` for the formation in its gauge where the orientation is not
  observable, :meth:`Estimate.published <relloc.estimate.Estimate.published>`).
* **Pose.** The estimate's position: ``(x, y)``, and ``z`` where it is 3D (else 0); the
  orientation a pure rotation about z by the robot's published yaw (:func:`published_yaw`:
  its yaw in a 3D estimate, its heading in a 2D one) where there is one, else the identity.
* **Covariance.** ROS's row-major 6x6 over ``(x, y, z, roll, pitch, yaw)``, built by
  :func:`pose_covariance`: the estimate's position covariance in the x, y (and z) block (the
  "not estimated" value on its diagonal where the estimate has none for the robot); the
  published yaw's variance (its circular std squared) at (5, 5) where there is one; every other
  diagonal entry :data:`NOT_ESTIMATED` (1e6), every other off-diagonal entry 0. Why 1e6 and
  not 0 for roll, pitch and a 2D estimate's z: relloc measures none of them (a ground team's
  model is planar, and a floor is not), so a zero variance would claim a certainty nobody
  has, and a filter fusing the pose (``robot_localization``) would trust the z = 0 and
  identity roll/pitch absolutely; a large
  variance is what users of ROS tools (``robot_localization``, RViz, Foxglove) read as "not
  estimated", so the published pose claims what relloc knows and nothing more.

:func:`estimate_pose_msg` is the message (``rosbags``, any distribution: the layout is the same
in all), :func:`estimate_pose_cdr` the same message as little-endian CDR bytes, encoded without
``rosbags`` for the live hot path (:func:`~relloc.ros.cdr.encode_pose_with_covariance_stamped`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from relloc.estimate import Estimate
from relloc.ros.cdr import encode_pose_with_covariance_stamped, split_stamp
from relloc.ros.codec import typestore

__all__ = [
    "NOT_ESTIMATED",
    "EstimatePose",
    "estimate_pose",
    "estimate_pose_cdr",
    "estimate_pose_msg",
    "pose_covariance",
    "published_yaw",
]

NOT_ESTIMATED = 1e6
"""Variance (m^2, rad^2) published for what relloc does not estimate (see the module docstring)."""

_MSGTYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"


def pose_covariance(
    xy: Sequence[Sequence[float]] | None, yaw_variance: float | None = None
) -> list[float]:
    """The row-major 6x6 ROS covariance (36 floats) of an estimate: ``xy`` the 2x2 one of
    ``(x, y)``, or the 3x3 one of ``(x, y, z)`` (``None``: not estimated), ``yaw_variance``
    yaw's (``None``: not estimated); what is not given (z in 2D, roll and pitch)
    :data:`NOT_ESTIMATED`."""
    cov = [0.0] * 36
    for i in range(6):
        cov[7 * i] = NOT_ESTIMATED
    if xy is not None:
        for i, row in enumerate(xy):
            for j, value in enumerate(row):
                cov[6 * i + j] = float(value)
    if yaw_variance is not None:
        cov[35] = float(yaw_variance)
    return cov


def published_yaw(est: Estimate, robot: str) -> tuple[float, float] | None:
    """``robot``'s yaw ``(mean, std)`` (rad) that its pose carries, ``None`` where there is none:
    in a 3D estimate its yaw in the estimate's frame (:attr:`Estimate.yaws`), what a flying
    team's estimator publishes for every robot; in a 2D one the heading estimate
    (:attr:`Estimate.headings`), as 2D poses have always carried."""
    return (est.yaws if est.dimension == 3 else est.headings).get(robot)


@dataclass(frozen=True)
class EstimatePose:
    """What one robot's pose message carries (the fields of a ``PoseWithCovarianceStamped``)."""

    t: float
    frame_id: str
    x: float
    y: float
    yaw: float
    covariance: list[float]
    """Row-major 6x6 over ``(x, y, z, roll, pitch, yaw)``."""
    z: float = 0.0


def estimate_pose(est: Estimate, robot: str) -> EstimatePose:
    """``robot``'s entry of what ``est`` publishes (:meth:`Estimate.published`: the formation
    in its gauge, frame ``<reference>/formation``, where the orientation is not observable) by
    the convention of the module docstring."""
    est = est.published()
    position = est.positions[robot]
    heading = published_yaw(est, robot)
    return EstimatePose(
        t=est.t,
        frame_id=est.frame_id,
        x=float(position[0]),
        y=float(position[1]),
        z=float(position[2]) if len(position) > 2 else 0.0,
        yaw=float(heading[0]) if heading is not None else 0.0,
        covariance=pose_covariance(
            est.covariances.get(robot),
            float(heading[1]) ** 2 if heading is not None else None,
        ),
    )


def estimate_pose_msg(est: Estimate, robot: str, distro: str | None = None) -> Any:
    """``robot``'s entry of ``est`` as a ``geometry_msgs/msg/PoseWithCovarianceStamped``."""
    p = estimate_pose(est, robot)
    types = (typestore(distro) if distro else typestore()).types
    sec, nanosec = split_stamp(p.t)
    stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    header = types["std_msgs/msg/Header"](stamp=stamp, frame_id=p.frame_id)
    point = types["geometry_msgs/msg/Point"](x=p.x, y=p.y, z=p.z)
    half = p.yaw / 2.0
    quat = types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(half), w=math.cos(half))
    pose = types["geometry_msgs/msg/Pose"](position=point, orientation=quat)
    pwc = types["geometry_msgs/msg/PoseWithCovariance"](
        pose=pose, covariance=np.array(p.covariance, dtype=np.float64)
    )
    return types[_MSGTYPE](header=header, pose=pwc)


def estimate_pose_cdr(est: Estimate, robot: str) -> bytes:
    """:func:`estimate_pose_msg` as little-endian CDR: the bytes the Zenoh sink publishes."""
    p = estimate_pose(est, robot)
    return encode_pose_with_covariance_stamped(
        p.t, p.x, p.y, p.yaw, p.covariance, p.frame_id, z=p.z
    )
