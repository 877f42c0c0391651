"""Onboard views (``relloc serve --robot NAME``): each robot's own estimate of its teammates.

Five simulated robots (the ``multi`` scenario, a compass team) publish on loopback Zenoh; two
servers run as robots ``r0`` and ``r2`` would on board. Each publishes its teammates below
``relloc/<robot>/`` in its own body frame (``<robot>/base_link``), and its status names it
and whom it hears. Everything is waited on, never slept for.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
import pytest
from waiting import wait_until

from relloc.estimate import HEADING_FRAME, Estimate
from relloc.live import SIM_TIME_BASE, LiveServer, ServeOptions, publish_events
from relloc.live.sim_robots import sim_team_config
from relloc.ros.messages import POSE_WITH_COVARIANCE_STAMPED, decode
from relloc.simulator.scenarios import multi_scenario


def test_the_body_frame_turns_a_heading_frame_estimate_by_the_references_heading() -> None:
    est = Estimate(
        1.0,
        "pf",
        "a",
        {"b": (1.0, 0.0)},
        {"b": ((0.04, 0.0), (0.0, 0.01))},
        yaws={"b": (0.5, 0.1)},
        frame=HEADING_FRAME,
    )
    body = est.in_body_frame(math.pi / 2)  # the reference faces +y: b is on its right
    assert body.frame_id == "a/base_link"
    assert body.position("b") == pytest.approx([0.0, -1.0])
    assert np.asarray(body.covariances["b"]) == pytest.approx(np.array([[0.01, 0.0], [0.0, 0.04]]))
    assert body.yaws["b"][0] == pytest.approx(0.5 - math.pi / 2)
    assert body.in_body_frame(1.0) is body  # already in a body frame
    assert est.in_body_frame(math.nan) is est  # no heading: left as it is


class Views:
    """Every pose published below ``relloc/<onboard>/``: ``(onboard, robot, t, frame, xy)``."""

    def __init__(self, session: Any, onboard: tuple[str, ...], robots: tuple[str, ...]) -> None:
        self._lock = threading.Lock()
        self.rows: list[tuple[str, str, float, str, tuple[float, float]]] = []
        self._subs = [
            session.declare_subscriber(
                f"relloc/{me}/{robot}/pose",
                lambda s, me=me, robot=robot: self._on(me, robot, s),
            )
            for me in onboard
            for robot in robots
            if robot != me
        ]

    def _on(self, me: str, robot: str, sample: Any) -> None:
        msg = decode(sample.payload.to_bytes(), POSE_WITH_COVARIANCE_STAMPED)
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        p = msg.pose.pose.position
        with self._lock:
            self.rows.append((me, robot, t, msg.header.frame_id, (p.x, p.y)))

    def count(self) -> int:
        with self._lock:
            return len(self.rows)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


def test_each_robot_on_board_sees_its_teammates_in_its_own_body_frame(
    sessions: tuple[Any, Any],
) -> None:
    srv_session, client = sessions
    sim = multi_scenario(0, duration=24.0)
    config = sim_team_config(sim)
    onboard = ("r0", "r2")
    views = Views(client, onboard, config.robot_names)
    rate = 3.0
    servers = [
        LiveServer(
            config,
            srv_session,
            ServeOptions(clock_rate=rate, reorder_window=1.5, status_period=0.5, robot=me),
        )
        for me in onboard
    ]
    runners = []
    for server in servers:
        server.start()
        runners.append(threading.Thread(target=server.run, daemon=True))
        runners[-1].start()
    try:
        stats = publish_events(
            sim.events(), config, client, rate=rate, time_base=SIM_TIME_BASE, wait=10.0
        )
        for server in servers:
            assert wait_until(
                lambda s=server: s.source.stats.events.total() >= stats.messages, 30.0
            )
    finally:
        for server in servers:
            server.stop()
        for runner in runners:
            runner.join(timeout=30)
    try:
        expected = sum(
            len(e.published().positions) for s in servers for e in s.pipelines[0].estimates
        )
        assert wait_until(lambda: views.count() >= expected, timeout=20.0)
    finally:
        for server in servers:
            server.close()
        views.close()

    for me, server in zip(onboard, servers, strict=True):
        assert server.config.reference == me
        status = server.status()
        assert status["onboard"] == me and set(status["hears"]) == set(config.robot_names)
        mine = [row for row in views.rows if row[0] == me]
        assert {row[1] for row in mine} == set(config.robot_names) - {me}
        late = [row for row in mine if row[2] - SIM_TIME_BASE > 15.0]
        # its formation in a gauge until the orientation is resolved, then its body frame
        assert {row[3] for row in mine} <= {f"{me}/base_link", f"{me}/formation"}
        assert {row[3] for row in late} == {f"{me}/base_link"}
        errors = []
        for _, robot, t, _, xy in late:
            when = np.array([t - SIM_TIME_BASE])
            x0, y0, yaw0 = sim.true_poses(me, when)[0]
            x1, y1, _ = sim.true_poses(robot, when)[0]
            c, s = math.cos(yaw0), math.sin(yaw0)
            dx, dy = x1 - x0, y1 - y0
            truth = (c * dx + s * dy, -s * dx + c * dy)
            errors.append(math.dist(xy, truth))
        assert late and float(np.median(errors)) < 0.3, me
