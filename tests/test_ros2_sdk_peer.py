"""relloc's live commands against an independent ROS 2 peer: ROBOTIS' zenoh-ros2-sdk.

The SDK is a pure-Python rmw_zenoh client (its own type hashes, keys, attachments, liveliness
tokens): it stands in for ROS 2 robots of one distribution, and for a ROS 2 consumer of relloc's
poses. Its message definitions are written locally from the ``rosbags`` type store of Humble or
Jazzy (``sensor_msgs/Range`` differs: Jazzy's ends with ``float32 variance``, and has another
RIHS01 hash; Humble nodes write ``TypeHashNotSupported`` in keys); the SDK's git clones are
replaced by a recorder, and every run checks it recorded nothing. Everything is on loopback
(``relloc serve`` / ``sim-robots`` listen on 127.0.0.1 with a free port, multicast off). The
helpers are in :mod:`relloc.live.ros2_peer` and :mod:`relloc.live.peer_run`; ``scripts/ros2_peer_check.py`` is the measurement.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("zenoh_ros2_sdk")

from relloc.live.peer_run import (
    PeerRun,
    RellocProcess,
    TeamTopics,
    free_port,
    run_against_serve,
    wait_for,
)
from relloc.live.ros2_peer import (
    HASH_NOT_SUPPORTED,
    ODOMETRY,
    PEER_TYPES,
    POSE,
    RANGE,
    RANGE_HASHES,
    STRING,
    Ros2Peer,
    msg_text,
    offline_sdk,
    rihs01,
    write_messages,
)

PUBLISHED = {  # rosidl's own hashes (see tests/test_rmw_zenoh.py), the same in both distributions
    ODOMETRY: "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    POSE: "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
    STRING: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
}
_RUNS: dict[tuple[str, str], dict[str, Any]] = {}


def served(distro: str, serve_distro: str, factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The figures of one SDK team run against serve (run once per pair of distributions)."""
    key = (distro, serve_distro)
    if key not in _RUNS:
        work = factory.mktemp(f"peer_{distro}_serve_{serve_distro}")
        _RUNS[key] = run_against_serve(PeerRun(distro=distro, serve_distro=serve_distro), work)
    return _RUNS[key]


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_local_definitions_give_ros2s_hashes_and_relloc_agrees(distro: str, tmp_path: Path) -> None:
    """The SDK, fed the written definitions, hashes as rosidl does; relloc's hash of each
    distribution's Range is the SDK's."""
    from relloc.ros.type_hash import type_hash

    folder = write_messages(distro, tmp_path)
    assert ("float32 variance" in msg_text(distro, RANGE)) is (distro != "humble")
    assert (folder / "geometry_msgs" / "msg" / "Vector3.msg").is_file()
    hashes = {t: rihs01(t, folder) for t in PEER_TYPES}
    assert hashes[RANGE] == RANGE_HASHES[distro]
    assert {t: hashes[t] for t in PUBLISHED} == PUBLISHED
    assert type_hash(RANGE, distro) == RANGE_HASHES[distro]


def test_the_sdk_reads_the_folder_and_never_clones(tmp_path: Path) -> None:
    """A type in the folder is read from it; one missing is looked for in git, and the clone
    is recorded and refused (the SDK logs it and finds nothing)."""
    from zenoh_ros2_sdk import message_registry

    folder = write_messages("jazzy", tmp_path)
    with offline_sdk(folder) as attempts:
        registry = message_registry.get_registry()
        assert registry.get_msg_file_path(RANGE) == folder / "sensor_msgs" / "msg" / "Range.msg"
        assert attempts == []
        assert registry.get_msg_file_path("std_msgs/msg/Bool") is None
        assert attempts == ["common_interfaces"]
    assert message_registry._registry is None  # restored


@pytest.mark.slow
@pytest.mark.parametrize(
    ("distro", "serve_distro"),
    [("jazzy", "jazzy"), ("humble", "humble"), ("humble", "jazzy"), ("jazzy", "humble")],
)
def test_serve_localizes_a_team_published_by_the_sdk(
    distro: str, serve_distro: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """A clean 4-robot team, 30 simulated s at 6x, through SDK publishers with ``distro``'s
    definitions: serve (``--ros-distro serve_distro``: either reads both layouts of Range)
    takes every message, estimates every robot, and the SDK's subscribers get each pose,
    within 5 cm of the truth (median)."""
    out = served(distro, serve_distro, tmp_path_factory)
    assert out["clone_attempts"] == []
    assert out["serve_exit"] == 0, out["serve_output"]
    assert out["serve_received_all"], (out["sent"], out["transport"], out["serve_output"])
    assert out["rejected"] == {}  # no decode_error, no unknown_type
    transport = out["transport"]
    assert transport["unknown_type_hash"] == {} and transport["lost"] == {}
    assert transport["publishers"] == out["publishers"] == 10  # 4 odometry, 6 range pairs
    if "hash_not_supported" in transport:  # samples keyed TypeHashNotSupported: the Humble ones
        assert transport["hash_not_supported"] == (out["sent"] if distro == "humble" else 0)
    estimates = out["serve_estimates"]
    assert estimates > 250
    assert out["poses_received"] == {r: estimates for r in out["robots"] if r != out["reference"]}
    # the heading frame; the formation in its gauge only before motion resolves the orientation
    assert out["reference"] in out["pose_frames"]
    assert set(out["pose_frames"]) <= {out["reference"], f"{out['reference']}/formation"}
    for robot, median in out["ape_median_m"].items():
        assert out["ape_n"][robot] > 150
        assert median <= 0.05, (robot, out["ape_median_m"])


@pytest.mark.slow
@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_the_sdk_lists_serves_topics_with_the_distributions_hashes(
    distro: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """``ros2 topic list``/``info -v`` as the SDK sees them during a run: serve's pose and
    status publishers and its subscriptions, every one with ``distro``'s hash."""
    out = served(distro, distro, tmp_path_factory)
    others = [r for r in out["robots"] if r != out["reference"]]
    graph = out["topics"]
    for robot in others:
        assert graph[f"/relloc/{robot}/pose"] == [POSE]
    assert graph["/relloc/status"] == [STRING]
    assert all(graph[f"/{r}/odom"] == [ODOMETRY] for r in out["robots"])
    assert [t for t, types in graph.items() if RANGE in types]

    def expected(msgtype: str) -> str:
        if distro == "humble":
            return HASH_NOT_SUPPORTED
        return RANGE_HASHES[distro] if msgtype == RANGE else PUBLISHED[msgtype]

    for topic, info in out["endpoints"].items():
        assert info is not None, topic
        (msgtype,) = info["types"]
        relloc = info["publishers"] if topic.startswith("/relloc/") else info["subscribers"]
        assert ["relloc", expected(msgtype)] in [list(e) for e in relloc], (topic, info)
        assert all(h == expected(msgtype) for _, h in info["publishers"] + info["subscribers"])


@pytest.mark.slow
@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_an_sdk_subscriber_hears_sim_robots(distro: str, tmp_path: Path) -> None:
    """``relloc sim-robots --ros-interface rmw_zenoh --ros-distro <distro>`` (its own process):
    the SDK with that distribution's definitions receives every odometry and range message it
    sent, in that distribution's layout."""
    port = free_port()
    config, summary = tmp_path / "team.toml", tmp_path / "sim.json"
    messages = write_messages(distro, tmp_path / "msg")
    args = [
        "sim-robots", "--scenario", "multi", "--ros-interface", "rmw_zenoh", "--ros-distro",
        distro, "--rate", "4", "--duration", "6", "--wait", "30", "--no-ground-truth",
        "--write-config", str(config), "--json", str(summary),
    ]  # fmt: skip
    with RellocProcess(args, port) as sim, Ros2Peer(distro, messages, port) as peer:
        topics = TeamTopics.load(config)
        odom = {r: peer.subscribe(t, ODOMETRY) for r, t in topics.odom.items()}
        ranges = {t: peer.subscribe(t, RANGE) for t in topics.range_topics()}
        assert wait_for(lambda: sim.proc.poll() is not None, 45.0), "sim-robots did not end"
        sent = json.loads(summary.read_text())["messages"]
        inboxes = [*odom.values(), *ranges.values()]
        assert wait_for(lambda: sum(i.count for i in inboxes) >= sent, 5.0)
        assert sim.stop() == 0, sim.output
        assert peer.clone_attempts == []
    assert sum(i.count for i in inboxes) == sent > 500
    assert all(inbox.count > 50 for inbox in odom.values())
    heard = {frozenset(t.split("/")[3:5]) for t, inbox in ranges.items() if inbox.count}
    assert len(heard) == math.comb(len(topics.nodes), 2)  # every pair, in some order
    rng = next(i for i in ranges.values() if i.count).snapshot()[0]
    assert 0.0 < rng.range < 15.0
    assert getattr(rng, "variance", None) == (None if distro == "humble" else 0.0)
    first = odom[topics.robots[1]].snapshot()[0]
    assert first.header.frame_id == "odom" and first.header.stamp.sec > 1_000_000_000
