"""A UWB driver's own message: Nooploop LinkTrack node frames give the ranges Range gives.

The shipped examples (``examples/uwb_drivers``) define ``nlink_parser/msg/LinktrackNodeframe2``
in both layouts in use: without a header (the ROS 1 driver and the first ROS 2 port) and with
``std_msgs/Header`` first (the current ROS 2 port). A simulated team's ranges are written once
as ``sensor_msgs/msg/Range`` per pair and once as node frames (one per range, listing its one
peer); the same filter on both recordings must give the same estimates.
"""

from __future__ import annotations

import dataclasses
import json
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from waiting import wait_until

from relloc.cli import main
from relloc.config import ConfigError, TeamConfig
from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth
from relloc.events import GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.live import (
    EstimateCollector,
    LiveServer,
    ReplayOptions,
    ServeOptions,
    replay_bag,
    simulated_team,
)
from relloc.live.publish import EventEncoder
from relloc.methods import build_pipeline
from relloc.ros import messages as rm
from relloc.ros.stores import custom_types, register_types
from relloc.sources.rosbag import RosbagSource

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "uwb_drivers"
FRAME = "nlink_parser/msg/LinktrackNodeframe2"
TOPIC = "/{robot}/nlink_linktrack_nodeframe2"
T_BASE = 1_700_000_000.0
DURATION = 20.0


def linktrack_config(config: TeamConfig, layout: str) -> TeamConfig:
    """``config`` with its ranges as LinkTrack node frames of the ``layout`` example."""
    uwb = dataclasses.replace(
        config.uwb,
        range_type=FRAME,
        range_topic=TOPIC,
        distance_field="nodes[].dis",
        peer_field="nodes[].id",
        msg_dirs=(str(EXAMPLES / layout),),
    )
    ids = {r.uwb_node: str(i + 1) for i, r in enumerate(config.robots)}  # LinkTrack ids are numbers
    robots = tuple(dataclasses.replace(r, uwb_node=ids[r.uwb_node]) for r in config.robots)
    pairs = {"-".join(ids[n] for n in key.split("-")): cal for key, cal in config.uwb.pairs.items()}
    return dataclasses.replace(config, uwb=dataclasses.replace(uwb, pairs=pairs), robots=robots)


def _frame(ev: RangeEvent, node: str, peer: str) -> Any:
    """A node frame of ``node`` listing one peer, stamped with the range's time if it can be."""
    msg = rm.zero_message(FRAME)
    peers = [
        rm.typestore().types["nlink_parser/msg/LinktrackNode2"](
            role=1, id=int(peer), dis=ev.distance, fp_rssi=0.0, rx_rssi=0.0
        )
    ]
    msg = dataclasses.replace(msg, id=int(node), nodes=peers)
    if hasattr(msg, "header"):
        msg = dataclasses.replace(
            msg, header=dataclasses.replace(msg.header, stamp=rm.time_msg(ev.t))
        )
    return msg


def write_bags(folder: Path, layout: str) -> tuple[Path, Path, TeamConfig, TeamConfig]:
    """The simulated team as two MCAP bags (ranges as Range, ranges as node frames of
    ``layout``), every message received at its own time; their two configs."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    sim, config = simulated_team(seed=0, duration=DURATION)
    frames = linktrack_config(config, layout)
    register_types(custom_types(EXAMPLES / layout))
    node_of = {r.name: r.uwb_node for r in frames.robots}
    encoder = EventEncoder(config, ground_truth=True)
    events = [
        ev for ev in sim.events() if isinstance(ev, OdometryEvent | RangeEvent | GroundTruthEvent)
    ]
    bags = folder / f"range_{layout}", folder / f"frames_{layout}"
    for bag, as_frames in zip(bags, (False, True), strict=True):
        with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            conns: dict[str, Any] = {}
            for ev in events:
                shifted = dataclasses.replace(ev, t=ev.t + T_BASE)
                if as_frames and isinstance(ev, RangeEvent):
                    topic, msgtype = TOPIC.format(robot=ev.robot_a), FRAME
                    payload = rm.encode(_frame(shifted, node_of[ev.robot_a], node_of[ev.robot_b]))
                else:
                    out = encoder.encode(ev, T_BASE)
                    assert out is not None
                    topic, msgtype, payload = out[0].name, out[0].msgtype, out[1]
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=rm.typestore())
                writer.write(conns[topic], round(shifted.t * 1e9), payload)
    return bags[0], bags[1], config, frames


def estimates(bag: Path, config: TeamConfig) -> tuple[RosbagSource, list[Any]]:
    source = RosbagSource(bag, config, ground_truth=False)
    pipeline = build_pipeline("pf", config.with_filter(particles=1000), seed=0)
    Engine([pipeline]).run(source)
    return source, pipeline.estimates


def _positions(found: list[Any]) -> np.ndarray:
    return np.array([[e.positions[r] for r in sorted(e.positions)] for e in found])


def ape_median(found: list[Any], reference: str) -> float:
    """Median position error (m) against the simulator's truth after a 5 s warm-up."""
    sim, _ = simulated_team(seed=0, duration=DURATION)
    truth = GroundTruth(reference)
    for ev in sim.events():
        if isinstance(ev, GroundTruthEvent):
            truth.add(ev)
    errors = []
    for e in found:
        t = e.t - T_BASE
        ref = truth.pose_at(reference, t)
        for robot, (x, y) in e.positions.items():
            p = truth.pose_at(robot, t)
            if t > 5.0 and p is not None and ref is not None:
                errors.append(float(np.hypot(x - (p[0] - ref[0]), y - (p[1] - ref[1]))))
    assert len(errors) > 100
    return float(np.median(errors))


@pytest.mark.parametrize("layout", ["linktrack_ros2", "linktrack_ros1"])
def test_node_frames_give_the_estimates_of_the_same_ranges_as_range(
    tmp_path: Path, layout: str
) -> None:
    ranges_bag, frames_bag, config, frames = write_bags(tmp_path, layout)
    plain_source, plain = estimates(ranges_bag, config)
    source, found = estimates(frames_bag, frames)
    assert source.stats.rejected == {} and plain_source.stats.rejected == {}
    assert source.stats.events["range"] == plain_source.stats.events["range"] > 100
    assert len(found) == len(plain)
    # `relloc run`, scored against the bags' motion capture: the same APE
    apes = []
    for bag, cfg in ((ranges_bag, config), (frames_bag, frames)):
        robots = tuple(dataclasses.replace(r, mocap_body=r.name) for r in cfg.robots)  # as encoded
        dataclasses.replace(cfg, robots=robots).with_filter(particles=1000).save(
            tmp_path / "team.toml"
        )
        out = tmp_path / f"{bag.name}.json"
        args = [
            "run",
            str(bag),
            "--config",
            str(tmp_path / "team.toml"),
            "--methods",
            "pf",
            "--warmup",
            "5",
        ]
        assert main([*args, "--json", str(out), "--no-progress"]) == 0
        (scenario,) = json.loads(out.read_text())["scenarios"].values()
        apes.append(scenario["methods"]["pf"]["mean_ape_median"])
    print(
        f"relloc run, mean APE median: as Range {apes[0]:.4f} m, as {layout} node frames {apes[1]:.4f} m"
    )
    assert apes[1] == pytest.approx(apes[0], abs=0.0 if layout == "linktrack_ros2" else 0.01)
    if layout == "linktrack_ros2":  # stamped: the very same events, the very same estimates
        assert np.array_equal(_positions(found), _positions(plain))
        assert source.stats.restamped == {}
    else:  # no header: receive times, equal to the stamps up to the bag's nanoseconds
        assert sum(source.stats.restamped.values()) == source.stats.events["range"]
        plain_ape, found_ape = (
            ape_median(plain, config.reference),
            ape_median(found, config.reference),
        )
        print(
            f"APE median: ranges as Range {plain_ape:.4f} m, as headerless node frames {found_ape:.4f} m"
        )
        assert found_ape == pytest.approx(plain_ape, abs=0.01)


def test_node_frames_replayed_over_zenoh(tmp_path: Path, sessions: tuple[Any, Any]) -> None:
    """The header layout's bag replayed into serve: every frame decoded, as many ranges fused
    as the bag holds, and the estimates of an offline run (a reorder window restores the order)."""
    _, frames_bag, _, frames = write_bags(tmp_path, "linktrack_ros2")
    offline_source, offline = estimates(frames_bag, frames)
    srv, client = sessions
    collector = EstimateCollector(client, frames)
    server = LiveServer(
        frames, srv, ServeOptions(particles=1000, seed=0, reorder_window=1.0, clock_rate=4.0)
    )
    server.start()
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        stats = replay_bag(frames_bag, frames, client, ReplayOptions(rate=4.0, wait=5.0))
        assert stats.unmatched == []
        assert wait_until(
            lambda: server.source.stats.events["range"] >= offline_source.stats.events["range"],
            timeout=20,
        )
    finally:
        server.stop()
        thread.join(timeout=10)
    summary = server.summary()["source"]
    collector.close()
    server.close()
    assert summary["rejected"] == {}
    assert summary["stats"]["events"]["range"] == offline_source.stats.events["range"]
    served = server.pipelines[0].estimates
    assert len(served) == pytest.approx(len(offline), abs=2)
    served_ape, offline_ape = (
        ape_median(served, frames.reference),
        ape_median(offline, frames.reference),
    )
    print(f"APE median: served {served_ape:.4f} m, offline {offline_ape:.4f} m")
    assert served_ape == pytest.approx(offline_ape, abs=0.01)


def test_a_type_relloc_cannot_load_is_a_clear_error_before_the_run(tmp_path: Path) -> None:
    _, config = simulated_team(seed=0, duration=1.0)
    broken = linktrack_config(config, "linktrack_ros2")
    missing = dataclasses.replace(
        broken,
        uwb=dataclasses.replace(
            broken.uwb, range_type="acme_uwb/msg/Ranges", msg_dirs=(str(tmp_path),)
        ),
    )
    with pytest.raises(ConfigError, match=rf"acme_uwb/msg/Ranges.*no definition found.*{tmp_path}"):
        _routes(missing)
    wrong = dataclasses.replace(
        broken, uwb=dataclasses.replace(broken.uwb, distance_field="nodes[].range")
    )
    with pytest.raises(ConfigError, match="LinktrackNode2 has no field 'range'"):
        _routes(wrong)
    lonely = dataclasses.replace(broken, uwb=dataclasses.replace(broken.uwb, peer_field=""))
    with pytest.raises(ConfigError, match="give peer_field too"):
        _routes(lonely)
    paired = dataclasses.replace(
        broken, uwb=dataclasses.replace(broken.uwb, range_topic="/uwb/{a}/{b}")
    )
    with pytest.raises(ConfigError, match=r"not \{b\}"):
        _routes(paired)


def _routes(config: TeamConfig) -> list[Any]:
    from relloc.sources.ingest import team_routes

    return team_routes(config)
