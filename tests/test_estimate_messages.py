"""One estimate reaches ROS the same way on every path: the Zenoh sink's CDR, the MCAP file.

The convention is :mod:`relloc.ros.estimate_msgs`'s; here one estimate, with a heading for one
robot and none for the other, must give the same header, position, orientation and 6x6
covariance (exactly) whether it is built by the Zenoh sink's path, decoded from the bytes that
sink puts on the wire, or written by the MCAP sink and read back by the ``mcap`` readers.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from relloc.config import RobotConfig, TeamConfig
from relloc.estimate import BODY_FRAME, Estimate
from relloc.ros import messages as rm
from relloc.ros.cdr import split_stamp
from relloc.ros.estimate_msgs import (
    NOT_ESTIMATED,
    estimate_pose,
    estimate_pose_cdr,
    estimate_pose_msg,
    pose_covariance,
)
from relloc.sinks.zenoh_sink import ZenohSink

make_reader = pytest.importorskip("mcap.reader").make_reader
DecoderFactory = pytest.importorskip("mcap_ros2.decoder").DecoderFactory

EST = Estimate(
    t=1_700_000_000.123456789,
    method="pf",
    reference="r0",
    positions={"r1": (1.25, -2.5), "r2": (-0.75, 3.0)},
    covariances={"r1": ((0.04, 0.01), (0.01, 0.09)), "r2": ((0.5, -0.125), (-0.125, 0.25))},
    headings={"r0": (0.0, 0.0), "r1": (0.3, 0.2)},
    frame=BODY_FRAME,
)
"""``r1`` has a heading, ``r2`` none."""


def expected_covariance(robot: str) -> np.ndarray:
    """The convention, written out: the estimate's xy block, 1e6 on z, roll, pitch, and on yaw
    without a heading, the heading's variance with one; nothing else."""
    cov = np.zeros((6, 6))
    cov[:2, :2] = EST.covariances[robot]
    cov[2, 2] = cov[3, 3] = cov[4, 4] = NOT_ESTIMATED
    heading = EST.headings.get(robot)
    cov[5, 5] = heading[1] ** 2 if heading else NOT_ESTIMATED
    return cov


class _Session:
    """A Zenoh session that keeps what is put: ``key -> [payload]``."""

    def __init__(self) -> None:
        self.puts: dict[str, list[bytes]] = {}

    def declare_publisher(self, key: str) -> Any:
        puts = self.puts.setdefault(key, [])
        return SimpleNamespace(put=lambda payload, attachment=None: puts.append(bytes(payload)))


def zenoh_payloads() -> dict[str, bytes]:
    """The bytes the Zenoh sink publishes for :data:`EST`, per robot."""
    config = TeamConfig(
        robots=tuple(RobotConfig(name=r) for r in ("r0", "r1", "r2")), reference="r0"
    )
    session = _Session()
    sink = ZenohSink(session, config)
    sink(EST)
    return {robot: session.puts[sink.key(robot, "pf")][-1] for robot in EST.positions}


def read_mcap(path: Path) -> dict[str, Any]:
    """Topic -> the one decoded message on it."""
    out: dict[str, Any] = {}
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages():
            out[channel.topic] = decoded
    return out


def fields(msg: Any) -> tuple[Any, ...]:
    """Header, position, orientation and covariance of a decoded pose message."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return (
        (int(msg.header.stamp.sec), int(msg.header.stamp.nanosec), str(msg.header.frame_id)),
        (float(p.x), float(p.y), float(p.z)),
        (float(q.x), float(q.y), float(q.z), float(q.w)),
        np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6),
    )


@pytest.mark.parametrize("robot", ["r1", "r2"], ids=["heading", "no-heading"])
def test_one_estimate_one_message_on_every_path(robot: str, tmp_path: Path) -> None:
    from relloc.sinks.mcap import write_mcap

    built = fields(estimate_pose_msg(EST, robot))
    wire = zenoh_payloads()[robot]
    assert wire == estimate_pose_cdr(EST, robot)
    assert wire == rm.encode(estimate_pose_msg(EST, robot), rm.POSE_WITH_COVARIANCE_STAMPED)
    decoded = fields(rm.decode(wire, rm.POSE_WITH_COVARIANCE_STAMPED))
    engine = SimpleNamespace(pipelines=[SimpleNamespace(name="pf", estimates=[EST])])
    path = write_mcap(tmp_path / "e.mcap", engine, None, distro="jazzy")  # type: ignore[arg-type]
    recorded = fields(read_mcap(path)[f"/relloc/pf/{robot}/pose"])

    for got in (decoded, recorded):
        assert got[:3] == built[:3]
        np.testing.assert_array_equal(got[3], built[3])
    header, position, orientation, cov = built
    assert header == (*split_stamp(EST.t), "r0/base_link")
    assert position == (*EST.positions[robot], 0.0)
    np.testing.assert_array_equal(cov, expected_covariance(robot))
    yaw = EST.headings[robot][0] if robot in EST.headings else 0.0
    assert orientation == (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def test_convention_without_a_position_covariance() -> None:
    est = Estimate(t=1.0, method="pf", reference="r0", positions={"r1": (0.0, 1.0)})
    p = estimate_pose(est, "r1")
    assert p.frame_id == "r0" and p.yaw == 0.0
    assert (
        p.covariance
        == pose_covariance(None)
        == [NOT_ESTIMATED if i % 7 == 0 else 0.0 for i in range(36)]
    )
