"""``relloc serve --record``: a live run of the simulated team into an MCAP file, stopped by
SIGTERM, read back with the independent ``mcap`` / ``mcap-ros2-support`` reader.

``relloc sim-robots`` (20 s of the multi scenario at twice real time) and ``relloc serve`` run
as processes, peers on 127.0.0.1 with multicast off; the test's own session hears what serve
publishes (poses and status). Every wait is on a condition, never on a guess at the machine's
speed.
"""

from __future__ import annotations

import json
import signal
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from processes import relloc, write_sim_team
from waiting import wait_until

from relloc.config import TeamConfig
from relloc.live import EstimateCollector, ZenohOptions, free_tcp_port, open_session
from relloc.ros.interfaces import RosInterface

make_reader = pytest.importorskip("mcap.reader").make_reader
DecoderFactory = pytest.importorskip("mcap_ros2.decoder").DecoderFactory

REPO = Path(__file__).resolve().parents[1]


def read_mcap(path: Path) -> dict[str, list[tuple[str, int, Any]]]:
    """Topic -> [(schema name, log time in ns, decoded message)], in log-time order."""
    out: dict[str, list[tuple[str, int, Any]]] = defaultdict(list)
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            out[channel.topic].append((schema.name, message.log_time, decoded))
    return out


def test_serve_records_what_it_publishes_to_mcap(tmp_path: Path) -> None:
    team, record, summary_path = (
        tmp_path / "team.toml",
        tmp_path / "live.mcap",
        tmp_path / "serve.json",
    )
    write_sim_team(team)
    config = TeamConfig.load(team)
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    t0 = time.time()
    serve = relloc(
        "serve", "--config", str(team), "--clock-rate", "2", "--json", str(summary_path), "--record", str(record),
        "--listen", endpoint, "--no-multicast", log=tmp_path / "serve.log",
    )  # fmt: skip
    procs = [serve]
    session = open_session(ZenohOptions(connect=(endpoint,), multicast=False))
    status: list[dict[str, Any]] = []
    try:
        collector = EstimateCollector(
            session, config, interface=RosInterface(distro=config.ros_distro)
        )
        session.declare_subscriber(
            "relloc/status", lambda s: status.append(json.loads(s.payload.to_bytes()))
        )
        # the team starts once the test hears serve (its status, every second): the test's
        # subscribers have reached serve before the first estimate
        assert wait_until(lambda: bool(status), timeout=60.0), (tmp_path / "serve.log").read_text()
        sim = relloc(
            "sim-robots", "--scenario", "multi", "--config", str(team), "--rate", "2", "--duration", "20",
            "--no-ground-truth", "--json", str(tmp_path / "sim.json"), "--no-multicast", "--connect", endpoint,
            log=tmp_path / "sim.log",
        )  # fmt: skip
        procs.append(sim)
        assert sim.wait(timeout=120) == 0, (tmp_path / "sim.log").read_text()
        sent = json.loads((tmp_path / "sim.json").read_text())["messages"]
        # serve has every message (its status says so) and the test every estimate of it so far
        assert wait_until(
            lambda: bool(status) and status[-1]["source"]["messages"] == sent, timeout=30.0
        ), status[-1:]
        assert wait_until(
            lambda: len(collector.estimates()) == status[-1]["methods"]["pf"]["estimates"],
            timeout=30.0,
        ), (len(collector.estimates()), status[-1]["methods"]["pf"])
        serve.send_signal(signal.SIGTERM)
        assert serve.wait(timeout=30) == 0, (tmp_path / "serve.log").read_text()
        published = collector.estimates()
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        session.close()
    wall = time.time() - t0

    summary = json.loads(summary_path.read_text())
    n = summary["methods"]["pf"]["estimates"]
    topics = read_mcap(record)
    print(f"\nserve --record: {record.stat().st_size} bytes, {n} estimates, "
          f"{sum(map(len, topics.values()))} messages, {wall:.1f} s")  # fmt: skip
    assert summary["record"] == {"path": str(record), "messages": sum(map(len, topics.values()))}
    assert not list(tmp_path.glob(".relloc-mcap-*"))  # the temporary rosbag2 folder is gone

    # One channel per robot, one pose per estimate published, and one status per estimate
    robots = config.others
    poses = {t for t in topics if t.endswith("/pose")}
    assert poses == {f"/relloc/pf/{r}/pose" for r in robots}
    assert n > 50
    for robot in robots:
        got = topics[f"/relloc/pf/{robot}/pose"]
        assert len(got) == n
        assert {schema for schema, _, _ in got} == {"geometry_msgs/msg/PoseWithCovarianceStamped"}
    status_msgs = topics["/relloc/pf/status"]
    assert len(status_msgs) == n
    assert all(schema == "diagnostic_msgs/msg/DiagnosticArray" for schema, _, _ in status_msgs)
    assert {kv.key for kv in status_msgs[-1][2].status[0].values} == {
        "orientation_observable",
        "inconsistent",
        "recovering",
    }

    # The poses and covariances are the ones serve published on Zenoh (the last estimate, fused
    # as serve stopped, may not have reached the test before its session closed)
    assert n - 1 <= len(published) <= n
    for robot in robots:
        recorded = {
            m.header.stamp.sec + m.header.stamp.nanosec * 1e-9: m
            for _, _, m in topics[f"/relloc/pf/{robot}/pose"]
        }
        for est in published:
            msg = recorded[est.t]  # the stamp, as the collector rebuilds it
            assert msg.header.frame_id in (config.reference, f"{config.reference}/formation")
            pos = msg.pose.pose.position
            assert (pos.x, pos.y) == est.positions[robot]
            cov = np.array(msg.pose.covariance).reshape(6, 6)
            np.testing.assert_array_equal(cov[:2, :2], np.array(est.covariances[robot]))

    # The ranges are the ones serve fed its method
    ranges = [t for t in topics if t.startswith("/relloc/ranges/")]
    assert ranges and all(topics[t][0][0] == "sensor_msgs/msg/Range" for t in ranges)
    assert sum(len(topics[t]) for t in ranges) == summary["source"]["stats"]["events"]["range"]
