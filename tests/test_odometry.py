"""Odometry tracks: shared heading frame, scale, pose vs twist integration, interpolation."""

from __future__ import annotations

import math

import pytest

from relloc.events import OdometryEvent
from relloc.odometry import OdometryTrack


def test_pose_mode_rotates_and_scales_into_shared_frame() -> None:
    track = OdometryTrack(heading_offset=math.pi / 2, scale=2.0, mode="pose")
    track.add(OdometryEvent(0.0, "r", 0.0, 0.0, 0.0))
    track.add(OdometryEvent(1.0, "r", 1.0, 0.0, 0.0))
    x, y, yaw, ahead = track.pose_at(0.5)
    assert (x, y) == pytest.approx((0.0, 1.0))
    assert yaw == pytest.approx(math.pi / 2)
    assert ahead == 0.0


def test_twist_mode_ignores_a_frozen_orientation() -> None:
    """The shortbag's /cali/ topics freeze the pose's orientation; the twist still turns."""
    track = OdometryTrack(mode="twist")
    dt = 0.05
    # drive a quarter circle of radius 1 at 0.5 m/s: w = 0.5 rad/s for pi s
    n = round(math.pi / dt)
    for k in range(n + 1):
        track.add(OdometryEvent(k * dt, "r", 123.0, 456.0, 0.0, v=0.5, w=0.5))
    x, y, yaw, _ = track.pose_at(n * dt)
    turned = 0.5 * n * dt
    assert x == pytest.approx(123.0 + math.sin(turned), abs=0.01)
    assert y == pytest.approx(456.0 + 1.0 - math.cos(turned), abs=0.01)
    assert yaw == pytest.approx(turned, abs=1e-9)


def test_extrapolation_is_bounded() -> None:
    track = OdometryTrack(mode="pose", max_extrapolation=0.5)
    track.add(OdometryEvent(0.0, "r", 0.0, 0.0, 0.0, v=1.0))
    assert track.pose_at(10.0)[0] == pytest.approx(0.5)
    assert track.pose_at(10.0)[3] == pytest.approx(0.5)
    assert track.pose_at(-1.0)[0] == 0.0


def test_unknown_mode_is_an_error() -> None:
    with pytest.raises(ValueError):
        OdometryTrack(mode="magic")
