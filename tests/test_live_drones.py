"""A flying team live: simulated drones on Zenoh, ``smoother3d`` serving their 3D poses.

Five simulated quadrotors (the ``drones`` scenario) publish their odometry (with its height)
and UWB ranges as ROS 2 CDR on loopback; a live server running the ``smoother3d`` kind
publishes each drone's pose relative to the reference. The poses must carry the drones' own
heights (z, in the reference's level body frame) and a yaw with a positive, estimated variance
at (5, 5) of the 6x6 covariance. Everything is waited on (messages in, estimates out), never
slept for.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
import pytest
from waiting import wait_until

pytest.importorskip("zenoh", reason="eclipse-zenoh is not installed: no live engine")

from relloc.live import SIM_TIME_BASE, LiveServer, ServeOptions, publish_events
from relloc.live.sim_robots import sim_team_config
from relloc.ros.estimate_msgs import NOT_ESTIMATED
from relloc.ros.messages import POSE_WITH_COVARIANCE_STAMPED, decode
from relloc.simulator.flight import drones_scenario


class Poses:
    """Every pose message published on ``relloc/<robot>/pose``: ``(t, robot, xyz, yaw, cov)``."""

    def __init__(self, session: Any, robots: tuple[str, ...]) -> None:
        self._lock = threading.Lock()
        self.rows: list[tuple[float, str, tuple[float, float, float], float, list[float]]] = []
        self._subs = [
            session.declare_subscriber(
                f"relloc/{robot}/pose", lambda s, robot=robot: self._on(robot, s)
            )
            for robot in robots
        ]

    def _on(self, robot: str, sample: Any) -> None:
        msg = decode(sample.payload.to_bytes(), POSE_WITH_COVARIANCE_STAMPED)
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        yaw = 2.0 * math.atan2(q.z, q.w)
        row = (t, robot, (p.x, p.y, p.z), yaw, [float(c) for c in msg.pose.covariance])
        with self._lock:
            self.rows.append(row)

    def count(self) -> int:
        with self._lock:
            return len(self.rows)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


def test_a_flying_team_is_served_live_with_heights_and_yaws(sessions: tuple[Any, Any]) -> None:
    srv_session, client = sessions
    sim = drones_scenario(0, duration=12.0)
    config = sim_team_config(sim).with_filter(kind="smoother3d")
    assert config.dimension == 3
    rate = 2.0
    poses = Poses(client, config.others)
    # A reorder window of 1 s of header time (0.5 s of wall time at 2x): the publisher shares
    # this process, and on a loaded machine it falls behind; the window restores stamp order.
    server = LiveServer(
        config, srv_session, ServeOptions(clock_rate=rate, reorder_window=1.0, status_period=0.5)
    )
    server.start()
    runner = threading.Thread(target=server.run, daemon=True)
    runner.start()
    try:
        stats = publish_events(
            sim.events(), config, client, rate=rate, time_base=SIM_TIME_BASE, wait=10.0
        )
        assert stats.unmatched == []
        assert wait_until(lambda: server.source.stats.events.total() >= stats.messages, 30.0)
    finally:
        server.stop()
        runner.join(timeout=30)
    try:
        own = server.pipelines[0].estimates
        assert own and own[-1].dimension == 3
        # The last estimate is fused and published as the server ends: wait for all of it.
        expected = sum(len(e.published().positions) for e in own)
        assert wait_until(lambda: poses.count() >= expected, timeout=20.0)
    finally:
        server.close()
        poses.close()

    assert server.summary()["source"]["rejected"] == {}
    last_t = max(row[0] for row in poses.rows)
    last = {row[1]: row for row in poses.rows if row[0] == last_t}
    assert set(last) == set(config.others)
    t = last_t - SIM_TIME_BASE
    ref_xyz = sim.true_positions(config.reference, np.array([t]))[0]
    ref_yaw = float(sim.true_poses(config.reference, np.array([t]))[0, 2])
    heights = []
    for robot, (_, _, xyz, yaw, cov) in last.items():
        true_dz = float(sim.true_positions(robot, np.array([t]))[0, 2] - ref_xyz[2])
        true_dyaw = float(sim.true_poses(robot, np.array([t]))[0, 2]) - ref_yaw
        # z is the drone's height over the reference's (the level body frame), not 0 nor the
        # mirror image a range-only fit could settle in
        assert xyz[2] == pytest.approx(true_dz, abs=0.2), robot
        assert 0.0 < cov[14] < NOT_ESTIMATED, robot  # z's variance: estimated
        assert 0.0 < cov[35] < NOT_ESTIMATED, robot  # yaw's variance at (5, 5): estimated
        assert abs(math.remainder(yaw - true_dyaw, math.tau)) < 0.2, robot
        heights.append(xyz[2])
    assert max(heights) - min(heights) > 0.5  # each drone its own height
