"""ROS 2 distributions: Range's two layouts read everywhere, written in the configured one.

Humble's ``sensor_msgs/msg/Range`` has no ``variance``; Iron and later end with it. The hashes
below are those of the issue report and rosidl: a Jazzy node keys its ranges
``RIHS01_b42b6256...``, and rmw_zenoh for Humble writes ``TypeHashNotSupported`` instead of any
hash (ros2/rmw_zenoh, README and docs/design.md).
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest
from waiting import wait_until

from relloc.cli import main
from relloc.config import ConfigError, TeamConfig
from relloc.events import OdometryEvent, RangeEvent
from relloc.live import LiveServer, ServeOptions, publish_events, simulated_team
from relloc.ros import messages as rm
from relloc.ros.distros import (
    HASH_NOT_SUPPORTED,
    key_hash,
    layout_of_hash,
    layouts,
)
from relloc.ros.interfaces import BRIDGE, RMW_ZENOH, RosInterface, dds_type_name
from relloc.sources.rosbag import RosbagSource
from relloc.sources.zenoh_source import ZenohSource, ZenohSourceOptions

JAZZY_RANGE = "RIHS01_b42b62562e93cbfe9d42b82fe5994dfa3d63d7d5c90a317981703f7388adff3a"
HUMBLE_RANGE = "RIHS01_9430b1915b94d4268ff903679e8ecd09b6a67d331bd028738ec1eeb592891ebd"
T0 = 1_700_000_000.0


def _range(distro: str, t: float = T0, d: float = 2.5) -> bytes:
    return rm.encode(rm.range_msg(RangeEvent(t, "", "", d), distro=distro))


def test_range_has_two_layouts_with_the_hashes_ros_publishes() -> None:
    found = layouts(rm.RANGE)
    assert [lay.hash for lay in found] == [JAZZY_RANGE, HUMBLE_RANGE]  # the default, jazzy, first
    assert [lay.name for lay in found] == ["iron..rolling", "humble"]
    assert [lay.hash for lay in layouts(rm.RANGE, "humble")] == [HUMBLE_RANGE, JAZZY_RANGE]
    assert found[0].fields[-1] == "variance" and "variance" not in found[1].fields
    assert len(layouts(rm.ODOMETRY)) == 1  # identical in every distribution
    assert key_hash(rm.RANGE, "jazzy") == key_hash(rm.RANGE, "kilted") == JAZZY_RANGE
    assert key_hash(rm.RANGE, "humble") == key_hash(rm.ODOMETRY, "humble") == HASH_NOT_SUPPORTED
    assert layout_of_hash(rm.RANGE, HUMBLE_RANGE) is found[1]
    assert layout_of_hash(rm.RANGE, HASH_NOT_SUPPORTED) is None


def test_decode_reads_either_layout_and_encode_writes_the_asked_one() -> None:
    humble, jazzy = _range("humble"), _range("jazzy")
    assert len(jazzy) == len(humble) + 4
    assert rm.decode(humble, rm.RANGE).range == rm.decode(jazzy, rm.RANGE).range == 2.5
    assert rm.in_distro(humble, rm.RANGE, "jazzy") == jazzy
    assert rm.in_distro(jazzy, rm.RANGE, "humble") == humble
    assert rm.in_distro(humble, rm.RANGE, "humble") is humble
    with pytest.raises(rm.MessageDecodeError, match="in layout humble"):
        rm.decode(jazzy, rm.RANGE, layouts(rm.RANGE)[1])


def test_config_and_interface_know_the_distributions() -> None:
    _, config = simulated_team(seed=0, duration=1.0)
    assert config.ros_distro == "jazzy"
    with pytest.raises(ConfigError, match=r"ros_distro: expected one of .*'humble'.*got 'foxy'"):
        TeamConfig.from_dict({**config.to_dict(), "ros_distro": "foxy"})
    with pytest.raises(ConfigError, match="unknown ROS 2 distribution 'ardent'"):
        RosInterface(RMW_ZENOH, 0, "ardent")


@pytest.mark.parametrize("server_distro", ["jazzy", "humble"])
def test_rmw_source_picks_the_layout_from_the_hash_and_tries_each_without_one(
    server_distro: str,
) -> None:
    _, config = simulated_team(seed=0, duration=1.0)
    iface = RosInterface(RMW_ZENOH, 0, server_distro)
    src = ZenohSource(config, ZenohSourceOptions(interface=iface))
    topic_key = next(k for k, r in src.routes.items() if r.kind == "range")
    head = f"{topic_key}/{dds_type_name(rm.RANGE)}"
    src.handle(f"{head}/{JAZZY_RANGE}", _range("jazzy", T0), T0)  # a Jazzy node
    src.handle(f"{head}/{HASH_NOT_SUPPORTED}", _range("humble", T0 + 0.1), T0)  # a Humble node
    src.handle(f"{head}/RIHS01_{'0' * 64}", _range("jazzy", T0 + 0.2), T0)  # unknown: tried
    src.handle(f"{head}/{HUMBLE_RANGE}", _range("jazzy", T0 + 0.3), T0)  # a lie: not decoded
    events = [a.event for a in src.flush()]
    assert [e.t - T0 for e in events] == pytest.approx([0.0, 0.1, 0.2])
    assert {e.distance for e in events} == {2.5}
    assert src.stats.rejected == {"decode_error": 1}
    assert src.stats.layouts == {f"{rm.RANGE}@iron..rolling": 2, f"{rm.RANGE}@humble": 1}
    tr = src.transport
    assert (tr.layout_by_hash, tr.hash_not_supported, tr.unknown_type_hash.total()) == (2, 1, 1)


def test_the_bridge_accepts_every_layout() -> None:
    _, config = simulated_team(seed=0, duration=1.0)
    src = ZenohSource(config, ZenohSourceOptions(interface=RosInterface(BRIDGE)))
    key = next(k for k, r in src.routes.items() if r.kind == "range")
    src.handle(key, _range("humble", T0), T0)
    src.handle(key, _range("jazzy", T0 + 0.1), T0)
    assert [a.event.distance for a in src.flush()] == [2.5, 2.5]
    assert src.stats.rejected == {}


def _bag_messages(config: TeamConfig) -> list[tuple[str, str, float, Any]]:
    r1, r2 = config.robots[0], config.robots[1]
    topic = config.uwb.range_topic.format(a=r1.uwb_node, b=r2.uwb_node)
    out = []
    for k in range(20):
        t = T0 + 0.1 * k
        for r in config.robots:
            odom = OdometryEvent(t, r.name, 0.01 * k, 0.0, 0.0, 0.1, 0.0)
            out.append((r.odom_topic or f"/{r.name}/odom", rm.ODOMETRY, t, rm.odometry_msg(odom)))
        out.append((topic, rm.RANGE, t + 0.01, rm.range_msg(RangeEvent(t, "", "", 1.0 + 0.1 * k))))
    return out


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_bags_of_either_distribution_give_the_same_events(
    tmp_path: Path, bag_writer: Any, storage: str
) -> None:
    """The layout comes from the bag's stored definition, whatever the configured distribution."""
    _, config = simulated_team(seed=0, duration=1.0)
    config = TeamConfig.from_dict({**config.to_dict(), "ros_distro": "humble"})
    events = {}
    for distro in ("humble", "jazzy"):
        bag = bag_writer(tmp_path / distro, _bag_messages(config), storage=storage, distro=distro)
        source = RosbagSource(bag, config, ground_truth=False)
        range_topic = next(t for t, kind in source.topics.items() if kind == "range")
        assert source.layouts[range_topic].distros[0] == (
            "humble" if distro == "humble" else "iron"
        )
        events[distro] = list(source)
        assert source.stats.rejected == {}
        assert sum(n for k, n in source.stats.layouts.items() if k.startswith(rm.RANGE)) == 20
    assert events["humble"] == events["jazzy"]
    assert len(events["jazzy"]) == 20 * (len(config.robots) + 1)


def test_write_config_records_the_interface_and_distribution(tmp_path: Path) -> None:
    team = tmp_path / "team.toml"
    args = [
        "sim-robots",
        "--write-config",
        str(team),
        "--config-only",
        "--ros-interface",
        "rmw_zenoh",
    ]
    assert main([*args, "--ros-distro", "humble"]) == 0
    config = TeamConfig.load(team)
    assert (config.ros_interface, config.ros_distro) == ("rmw_zenoh", "humble")
    assert main(args) == 0
    assert TeamConfig.load(team).ros_distro == "jazzy"


def _serve(
    sessions: tuple[Any, Any], robots: RosInterface, server: RosInterface
) -> tuple[LiveServer, list[str], list[str]]:
    """A simulated team published as ``robots`` to a server on ``server``: the server, every
    data key seen on the client and every liveliness token."""
    srv_session, client = sessions
    sim, config = simulated_team(seed=0, duration=4.0)
    keys: set[str] = set()
    lock = threading.Lock()

    def seen(sample: Any) -> None:
        with lock:
            keys.add(str(sample.key_expr))

    sub = client.declare_subscriber("0/**", seen)
    live = LiveServer(
        config, srv_session, ServeOptions(particles=500, clock_rate=4.0, interface=server)
    )
    live.start()
    thread = threading.Thread(target=live.run, daemon=True)
    thread.start()
    try:
        stats = publish_events(
            sim.events(), config, client, rate=4.0, interface=robots, time_base=T0, wait=5.0
        )
        assert stats.unmatched == []
        assert wait_until(lambda: live.source.stats.events.total() >= stats.messages)
        assert wait_until(lambda: any("/pose/" in k for k in keys))
        tokens = [str(r.ok.key_expr) for r in client.liveliness().get("@ros2_lv/0/**", timeout=2.0)]
    finally:
        live.stop()
        thread.join(timeout=10)
        sub.undeclare()
    live.close()
    with lock:
        return live, sorted(keys), tokens


def test_humble_keys_and_tokens_carry_type_hash_not_supported(sessions: tuple[Any, Any]) -> None:
    """``--ros-distro humble``: every data key (``<domain>/<name>/<type>/<hash>``) and every
    endpoint token (``.../MP|MS/<enclave>/<ns>/<node>/<topic>/<type>/<hash>/<qos>``) relloc
    declares carries ``TypeHashNotSupported``; the ranges decode, tried in each layout."""
    humble = RosInterface(RMW_ZENOH, 0, "humble")
    server, keys, tokens = _serve(sessions, humble, humble)
    assert len(keys) > 10 and all(k.split("/")[-1] == HASH_NOT_SUPPORTED for k in keys)
    endpoints = [t.split("/") for t in tokens if t.split("/")[5] in ("MP", "MS")]
    assert len(endpoints) > 10 and all(t[11] == HASH_NOT_SUPPORTED for t in endpoints)
    summary = server.summary()["source"]
    assert summary["rejected"] == {} and summary["layouts"][f"{rm.RANGE}@humble"] > 0
    assert summary["transport"]["hash_not_supported"] == sum(summary["stats"]["messages"].values())


def test_a_jazzy_server_serves_a_humble_team(sessions: tuple[Any, Any]) -> None:
    server, keys, _ = _serve(
        sessions, RosInterface(RMW_ZENOH, 0, "humble"), RosInterface(RMW_ZENOH, 0)
    )
    summary = server.summary()["source"]
    assert summary["rejected"] == {} and summary["layouts"][f"{rm.RANGE}@humble"] > 0
    poses = [k for k in keys if "/pose/" in k]
    assert poses and all(
        k.endswith(key_hash(rm.POSE_WITH_COVARIANCE_STAMPED, "jazzy")) for k in poses
    )
    assert len(server.pipelines[0].estimates) > 5
