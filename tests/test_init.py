"""``relloc init``: a team config drafted from a bag (robots, UWB node mapping, quirks).

A synthetic bag checks the decisions without shared data; the TIERS recordings check them
against the shipped configs' node mappings, and the drafted shortbag config against the shipped
one's APE.
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from relloc.cli import main
from relloc.config import TeamConfig
from relloc.events import GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.ros.messages import (
    ODOMETRY,
    POSE_STAMPED,
    TRANSFORM_STAMPED,
    odometry_msg,
    pose_stamped_msg,
    quaternion_from_yaw,
    range_msg,
    typestore,
)
from relloc.sources.inspect_bag import assign_nodes, inspect_bag, mocap_patterns

NODES = {"tb1": "n_5", "tb2": "n_9", "tb3": "n_2"}
"""The synthetic team's node mapping (deliberately not n_k on robot k)."""
VRPN = "/vrpn_client_node/{body}/pose"


def _mocap_msg(msgtype: str, t: float, name: str, x: float, y: float) -> Any:
    """A motion-capture pose of one of the types ``relloc init`` finds motion capture by."""
    if msgtype == ODOMETRY:
        return odometry_msg(OdometryEvent(t, name, x, y, 0.2), frame_id="world")
    if msgtype == TRANSFORM_STAMPED:
        types = typestore().types
        ts = pose_stamped_msg(GroundTruthEvent(t, name, (x, y), 0.2))
        transform = types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
            rotation=quaternion_from_yaw(0.2),
        )
        return types[TRANSFORM_STAMPED](header=ts.header, child_frame_id=name, transform=transform)
    return pose_stamped_msg(GroundTruthEvent(t, name, (x, y), 0.2))


def _synthetic_bag(
    path: Path,
    bag_writer: Callable[..., Path],
    mocap: str = VRPN,
    mocap_type: str = POSE_STAMPED,
    body: str = "{name}_cap",
    decoy: str = "",
) -> Path:
    """Three robots driving circles for 20 s; ranges = distance + 0.3 m (+ noise); tb2's odometry
    has zero stamps, tb3's a frozen orientation; an extra node n_7 ranges only to n_5. Motion
    capture (none if empty) on ``mocap`` (with ``{body}``: ``body`` of the robot's name) as ``mocap_type``;
    ``decoy`` (with ``{body}``) adds a PoseStamped topic per robot that is not motion capture."""
    rng = np.random.default_rng(1)
    centres = {"tb1": (0.0, 0.0), "tb2": (4.0, 1.0), "tb3": (1.0, 4.0)}
    msgs = []

    def pos(name: str, t: float) -> tuple[float, float]:
        cx, cy = centres[name]
        k = int(name[-1])
        return cx + math.cos(0.3 * k * t + k), cy + math.sin(0.3 * k * t + k)

    for i in range(400):
        t = 100.0 + 0.05 * i
        for name in NODES:
            x, y = pos(name, t)
            if mocap:
                topic = mocap.format(body=body.format(name=name))
                msgs.append((topic, mocap_type, t, _mocap_msg(mocap_type, t, name, x, y)))
            if decoy and i % 100 == 0:
                msgs.append(
                    (
                        decoy.format(body=name),
                        POSE_STAMPED,
                        t,
                        pose_stamped_msg(GroundTruthEvent(t, name, (1.0, 1.0))),
                    )
                )
            if i % 2 == 0:
                yaw = 0.0 if name == "tb3" else 0.1 * i
                stamp = 0.0 if name == "tb2" else t
                msgs.append(
                    (
                        f"/{name}/odom",
                        "nav_msgs/msg/Odometry",
                        t,
                        odometry_msg(OdometryEvent(stamp, name, x, y, yaw, v=0.3, w=0.3)),
                    )
                )
        names = list(NODES)
        for a in range(3):
            for b in range(a + 1, 3):
                na, nb = NODES[names[a]], NODES[names[b]]
                d = math.dist(pos(names[a], t), pos(names[b], t)) + 0.3 + rng.normal(0, 0.03)
                msgs.append(
                    (
                        f"/uwb/tof/{na}/{nb}/distance",
                        "sensor_msgs/msg/Range",
                        t,
                        range_msg(RangeEvent(t, "", "", d)),
                    )
                )
        msgs.append(
            (
                "/uwb/tof/n_7/n_5/distance",
                "sensor_msgs/msg/Range",
                t,
                range_msg(RangeEvent(t, "", "", 2.0)),
            )
        )
    return bag_writer(path, msgs)


def test_synthetic_bag_inventory_and_mapping(
    tmp_path: Path, bag_writer: Callable[..., Path]
) -> None:
    bag = _synthetic_bag(tmp_path / "bag", bag_writer)
    inv = inspect_bag(bag)
    assert inv.range_pattern == "/uwb/tof/{a}/{b}/distance"
    assert inv.range_layout != "humble"
    assert set(inv.nodes) == {"n_2", "n_5", "n_7", "n_9"}
    assert inv.odometry["/tb2/odom"].zero_stamps and not inv.odometry["/tb1/odom"].zero_stamps
    assert (
        inv.odometry["/tb3/odom"].frozen_orientation
        and not inv.odometry["/tb1/odom"].frozen_orientation
    )
    best = assign_nodes(inv, ["tb1_cap", "tb2_cap", "tb3_cap"])
    assert best[0].nodes == {f"{k}_cap": v for k, v in NODES.items()}
    assert best[0].rms < 0.1 < best[1].rms


def test_init_writes_a_loadable_config(tmp_path: Path, bag_writer: Callable[..., Path]) -> None:
    bag = _synthetic_bag(tmp_path / "bag", bag_writer)
    out = tmp_path / "team.toml"
    assert main(["init", str(bag), "--out", str(out)]) == 0
    cfg = TeamConfig.load(out)
    assert {r.name: r.uwb_node for r in cfg.robots} == NODES
    assert cfg.robot("tb2").odom_zero_stamps and cfg.robot("tb3").odom_mode == "twist"
    assert cfg.robot("tb1").odom_mode == "pose" and cfg.robot("tb1").mocap_body == "tb1_cap"
    assert cfg.ros_distro == "jazzy" and cfg.uwb.range_topic == "/uwb/tof/{a}/{b}/distance"
    assert cfg.mocap_topic == VRPN  # the vrpn naming, found by type like any other
    text = out.read_text()
    assert "n_7" in text and "reference:" in text  # the left-out node and the rule, as comments
    # never overwritten without --force
    out.write_text("# mine\n")
    assert main(["init", str(bag), "--out", str(out)]) == 2
    assert out.read_text() == "# mine\n"
    assert main(["init", str(bag), "--out", str(out), "--force"]) == 0
    assert TeamConfig.load(out).robot_names == ("tb1", "tb2", "tb3")


def test_init_finds_mocap_by_type_on_world_topics(
    tmp_path: Path, bag_writer: Callable[..., Path]
) -> None:
    """Mocap as PoseStamped on ``/<body>/world`` beside the robots' own ``/<robot>/odom``: a
    team of three, the right nodes, ``mocap_topic`` in the draft, calibrated from that mocap."""
    bag = _synthetic_bag(tmp_path / "bag", bag_writer, "/{body}/world", body="{name}")
    out = tmp_path / "team.toml"
    assert main(["init", str(bag), "--out", str(out)]) == 0
    cfg = TeamConfig.load(out)
    assert cfg.mocap_topic == "/{body}/world"
    assert {r.name: r.uwb_node for r in cfg.robots} == NODES
    assert {r.name: (r.mocap_body, r.odom_topic) for r in cfg.robots} == {
        n: (n, f"/{n}/odom") for n in NODES
    }
    assert len(cfg.uwb.pairs) == 3  # biases calibrated from the /<body>/world mocap
    assert all(0.25 < p.bias < 0.35 for p in cfg.uwb.pairs.values())
    assert cfg.robot("tb1").heading_offset_deg != 0.0
    # a ground team keeps the filter's range noise model (only a flying team's is measured)
    raw = tomllib.loads(out.read_text())["uwb"]
    assert "sigma" not in raw
    assert not any("bias_sigma" in p for p in raw["pairs"].values())  # nor its biases' errors


@pytest.mark.parametrize(
    ("mocap", "msgtype"),
    [("/mocap/{body}", TRANSFORM_STAMPED), ("/vicon/{body}/odom", ODOMETRY)],
)
def test_inspect_finds_mocap_of_other_types(
    tmp_path: Path, bag_writer: Callable[..., Path], mocap: str, msgtype: str
) -> None:
    bag = _synthetic_bag(tmp_path / "bag", bag_writer, mocap, msgtype, body="{name}")
    inv = inspect_bag(bag)
    assert (inv.mocap_pattern, inv.mocap_type) == (mocap, msgtype)
    assert set(inv.tracks) == set(NODES) and set(inv.odometry) == {f"/{n}/odom" for n in NODES}
    best = assign_nodes(inv, list(NODES))
    assert best[0].nodes == NODES


def test_mocap_patterns_rule() -> None:
    odom, pose = ODOMETRY, POSE_STAMPED
    topics = {
        "/tb1/odom": odom,
        "/tb2/odom": odom,
        "/cali/tb1/odom": odom,
        "/cali/tb2/odom": odom,
        "/tb1/goal_pose": pose,
        "/tb2/goal_pose": pose,
        "/mocap/tb1/pose": pose,
        "/mocap/tb2/pose": pose,
    }
    found = mocap_patterns(topics)
    assert [p.pattern for p in found] == ["/mocap/{body}/pose", "/{body}/goal_pose"]
    assert found[0].topics == {"/mocap/tb1/pose": "tb1", "/mocap/tb2/pose": "tb2"}
    (given,) = mocap_patterns(topics, "/{body}/goal_pose")
    assert set(given.topics.values()) == {"tb1", "tb2"}
    assert mocap_patterns(topics, "/{body}/world") == []


def test_init_mocap_topic_option(tmp_path: Path, bag_writer: Callable[..., Path]) -> None:
    """Two PoseStamped patterns with no motion-capture word: the draft names the runner-up, and
    --mocap-topic picks the right one."""
    bag = _synthetic_bag(
        tmp_path / "bag", bag_writer, "/{body}/truth", body="{name}", decoy="/{body}/goal"
    )
    out = tmp_path / "team.toml"
    main(["init", str(bag), "--out", str(out), "--no-calibrate"])
    assert "/{body}/truth" in out.read_text()  # named as the other pattern
    args = ["init", str(bag), "--out", str(out), "--force", "--mocap-topic", "/{body}/truth"]
    assert main(args) == 0
    cfg = TeamConfig.load(out)
    assert cfg.mocap_topic == "/{body}/truth"
    assert {r.name: r.uwb_node for r in cfg.robots} == NODES
    assert main([*args, "--mocap-topic", "/{body}/nothing"]) == 2


def test_init_without_mocap_names_types_and_option(
    tmp_path: Path, bag_writer: Callable[..., Path], capsys: pytest.CaptureFixture[str]
) -> None:
    bag = _synthetic_bag(tmp_path / "bag", bag_writer, mocap="")
    assert main(["init", str(bag), "--out", str(tmp_path / "x.toml")]) == 2
    err = capsys.readouterr().err
    assert "fewer than two motion-capture bodies" in err
    assert "PoseStamped" in err and "TransformStamped" in err and "--mocap-topic" in err


def _draft(shared: Path, bag: str, tmp_path: Path, *extra: str) -> tuple[int, TeamConfig, str]:
    out = tmp_path / "draft.toml"
    rc = main(["init", str(shared / bag), "--out", str(out), "--force", *extra])
    return rc, TeamConfig.load(out), out.read_text()


def test_tiers_shortbag_mapping(shared_data: Path, tmp_path: Path) -> None:
    rc, cfg, _ = _draft(shared_data, "tiers/multi4_shortbag_20221011", tmp_path)
    shipped = TeamConfig.load(
        Path(__file__).parents[1] / "configs/tiers/multi4_shortbag_20221011.toml"
    )
    assert rc == 0
    fields = ("name", "uwb_node", "mocap_body", "odom_topic", "odom_mode", "odom_zero_stamps")
    assert [[getattr(r, f) for f in fields] for r in cfg.robots] == [
        [getattr(r, f) for f in fields] for r in shipped.robots
    ]
    assert cfg.ros_distro == "humble"


def test_tiers_case4_mapping(shared_data: Path, tmp_path: Path) -> None:
    rc, cfg, text = _draft(shared_data, "tiers_uwb_rel/case4_test1_static", tmp_path)
    assert rc == 0
    assert {r.name: r.nodes for r in cfg.robots} == {
        f"turtlebot{k}": (f"n_{k}", "n_8") if k == 5 else (f"n_{k}",) for k in range(1, 8)
    }
    assert all(not r.odom_topic for r in cfg.robots)
    assert "second tag: n_8 on turtlebot5" in text and "left out" not in text
    assert len(cfg.uwb.pairs) == 27 and all(
        p.source == "case4_test1_static" for p in cfg.uwb.pairs.values()
    )
    rc, cfg, _ = _draft(shared_data, "tiers_uwb_rel/case4_test1_static", tmp_path, "--no-calibrate")
    assert rc == 0 and not cfg.uwb.pairs
    assert cfg.robot("turtlebot5").nodes == ("n_5", "n_8") and not cfg.has_lever_arms


SEEDS = (0, 1, 2)
"""One seed's APE moves by up to 0.05 m on the shortbag; the mean of three is compared."""


def _mean_ape(bag: Path, config: Path, tmp_path: Path) -> dict[str, float]:
    """Per-robot ``pf`` APE median of ``relloc run``, averaged over :data:`SEEDS`."""
    sums: dict[str, float] = {}
    for seed in SEEDS:
        out = tmp_path / f"{config.stem}-{seed}.json"
        args = ["run", str(bag), "--config", str(config), "--methods", "pf", "--seed", str(seed)]
        assert (
            main([*args, "--out", str(tmp_path / "out"), "--json", str(out), "--no-progress"]) == 0
        )
        (scenario,) = json.loads(out.read_text())["scenarios"].values()
        for robot, fig in scenario["methods"]["pf"]["robots"].items():
            sums[robot] = sums.get(robot, 0.0) + fig["ape_median"] / len(SEEDS)
    return sums


def test_tiers_shortbag_draft_runs_as_well_as_shipped(shared_data: Path, tmp_path: Path) -> None:
    """The draft (biases and heading offsets calibrated from the bag's mocap) at the shipped
    reference gives each robot's APE no more than 0.02 m above the shipped config's, over
    :data:`SEEDS` (a draft that does better also runs as well: with the compiled step turtle05
    is 0.095 m drafted, 0.123 m shipped)."""
    shipped_path = Path(__file__).parents[1] / "configs/tiers/multi4_shortbag_20221011.toml"
    shipped = TeamConfig.load(shipped_path)
    rc, cfg, _ = _draft(
        shared_data, "tiers/multi4_shortbag_20221011", tmp_path, "--reference", shipped.reference
    )
    assert rc == 0 and cfg.reference == shipped.reference and len(cfg.uwb.pairs) == 6
    assert cfg.robot("turtle01").heading_offset_deg == shipped.robot("turtle01").heading_offset_deg
    bag = shared_data / "tiers/multi4_shortbag_20221011"
    drafted, expected = (
        _mean_ape(bag, tmp_path / "draft.toml", tmp_path),
        _mean_ape(bag, shipped_path, tmp_path),
    )
    assert drafted.keys() == expected.keys()
    for robot, ape in expected.items():
        assert drafted[robot] - ape < 0.02, (robot, drafted, expected)


def test_tiers_pair_is_ambiguous_without_node(shared_data: Path, tmp_path: Path) -> None:
    rc, cfg, text = _draft(shared_data, "tiers/pair_range_20220907_1725", tmp_path)
    assert rc == 2 and "UNDECIDED" in text
    assert cfg.robot_names == ("turtle01", "turtle03")
    rc, cfg, text = _draft(
        shared_data, "tiers/pair_range_20220907_1725", tmp_path, "--node", "turtle01=n_2"
    )
    assert rc == 0 and "UNDECIDED" not in text
    assert {r.name: r.uwb_node for r in cfg.robots} == {"turtle01": "n_2", "turtle03": "n_3"}


def test_bad_node_argument(shared_data: Path, tmp_path: Path) -> None:
    out = tmp_path / "x.toml"
    assert (
        main(
            [
                "init",
                str(shared_data / "tiers/pair_range_20220907_1725"),
                "--out",
                str(out),
                "--node",
                "turtle01=n_9",
            ]
        )
        == 2
    )
    assert not out.exists()
