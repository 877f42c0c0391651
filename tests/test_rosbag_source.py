"""RosbagSource: ordering, clocks, topic routing, rejections and errors.

Synthetic bags (written with rosbags in tmp_path) pin the exact behaviour; the shared TIERS
recordings check it on the real data and its quirks (48-day clock offset, zero stamps, node ids).
"""

from __future__ import annotations

import hashlib
import math
import shutil
import sqlite3
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest

from relloc.config import CameraConfig, RobotConfig, TeamConfig
from relloc.events import DetectionEvent, Event, GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.ros import messages as rm
from relloc.sources.rosbag import BagError, RosbagSource

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "tiers"
OFFSET = -1000.0  # header clock minus receive clock in the synthetic bags


# ---------------------------------------------------------------------------- synthetic bags
def _types():
    return rm.typestore().types


def _pose_stamped(t: float, x: float, y: float, yaw: float):
    types = _types()
    header = types["std_msgs/msg/Header"](stamp=rm.time_msg(t), frame_id="world")
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=0.1),
        orientation=rm.quaternion_from_yaw(yaw),
    )
    return types[rm.POSE_STAMPED](header=header, pose=pose)


def _detections(t: float, positions: list[tuple[float, float, float]]):
    types = _types()
    dets = [
        types["depthai_ros_msgs/msg/SpatialDetection"](
            results=[types["vision_msgs/msg/ObjectHypothesis"](id="56", score=0.8)],
            bbox=types["vision_msgs/msg/BoundingBox2D"](
                center=types["geometry_msgs/msg/Pose2D"](x=0.0, y=0.0, theta=0.0),
                size_x=1.0,
                size_y=1.0,
            ),
            position=types["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
            is_tracking=False,
            tracking_id="",
        )
        for p in positions
    ]
    header = types["std_msgs/msg/Header"](stamp=rm.time_msg(t), frame_id="oak")
    return types[rm.SPATIAL_DETECTION_ARRAY](header=header, detections=dets)


def synthetic_messages() -> list[tuple[str, str, float, object]]:
    """Three robots over 3 s: mocap 50 Hz, odometry 20 Hz (r2 with zero stamps), ranges 10 Hz
    (one NaN, one negative, one repeat; plus a topic to an anchor node), detections 10 Hz
    stamped 0.3 s before reception (one with no depth)."""
    recv0 = 2000.0
    msgs: list[tuple[str, str, float, object]] = []
    for k in range(150):
        recv = recv0 + k * 0.02
        for body, (x, y) in (("b1", (k * 0.01, 0.0)), ("b2", (3.0, 1.0))):
            t = recv + OFFSET - 0.001
            msgs.append(
                (
                    f"/vrpn_client_node/{body}/pose",
                    rm.POSE_STAMPED,
                    recv,
                    _pose_stamped(t, x, y, 0.5),
                )
            )
    for k in range(60):
        recv = recv0 + 0.01 + k * 0.05
        ev1 = OdometryEvent(t=recv + OFFSET - 0.05, robot="r1", x=k * 0.025, y=0.0, yaw=0.1, v=0.5)
        msgs.append(("/r1/odom", rm.ODOMETRY, recv, rm.odometry_msg(ev1)))
        ev2 = OdometryEvent(t=0.0, robot="r2", x=0.0, y=0.0, yaw=0.0)
        msgs.append(("/r2/odom", rm.ODOMETRY, recv + 0.001, rm.odometry_msg(ev2)))
    values = [3.3, math.nan, -1.0, 3.2, 3.2] + [3.1 - 0.01 * k for k in range(25)]
    for k, d in enumerate(values):
        recv = recv0 + 0.03 + k * 0.1
        ev = RangeEvent(t=recv + OFFSET - 0.002, robot_a="", robot_b="", distance=d)
        msgs.append(("/uwb/tof/n_2/n_1/distance", rm.RANGE, recv, rm.range_msg(ev)))
        msgs.append(("/uwb/tof/n_1/n_5/distance", rm.RANGE, recv, rm.range_msg(ev)))
    for k in range(30):
        recv = recv0 + 0.05 + k * 0.1
        pos = [(0.2, 0.0, 2.0)] + ([(0.0, 0.0, 0.0)] if k == 3 else [])
        msgs.append(
            ("/r1/det", rm.SPATIAL_DETECTION_ARRAY, recv, _detections(recv + OFFSET - 0.3, pos))
        )
    msgs.sort(key=lambda m: m[2])
    return msgs


def synthetic_team(**changes: object) -> TeamConfig:
    robots = (
        RobotConfig(
            name="r1",
            uwb_node="n_1",
            odom_topic="/r1/odom",
            mocap_body="b1",
            detection_topic="/r1/det",
            detection_format="depthai",
            camera=CameraConfig(x=0.1),
        ),
        RobotConfig(name="r2", uwb_node="n_2", odom_topic="/r2/odom", mocap_body="b2"),
        RobotConfig(name="r3", uwb_node="n_9"),
    )
    return TeamConfig(robots=robots, reference="r2", name="synthetic", **changes)  # type: ignore[arg-type]


@pytest.fixture
def synthetic_bag(tmp_path: Path, bag_writer: Callable[..., Path]) -> Path:
    return bag_writer(tmp_path / "synthetic", synthetic_messages())


def _times(events: list[Event]) -> list[float]:
    return [e.t for e in events]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_synthetic_bag_events_in_header_order(
    tmp_path: Path, bag_writer: Callable[..., Path], storage: str
) -> None:
    bag = bag_writer(tmp_path / f"bag_{storage}", synthetic_messages(), storage=storage)
    src = RosbagSource(bag, synthetic_team())
    events = list(src)
    assert _times(events) == sorted(_times(events))
    assert src.stats.events == {"ground_truth": 300, "odometry": 120, "range": 28, "detection": 30}
    assert src.stats.rejected == {
        "range_nonfinite": 1,
        "range_nonpositive": 1,
        "detection_zero_position": 1,
    }
    assert src.stats.repeated_ranges == 1
    assert src.ignored_range_topics == ["/uwb/tof/n_1/n_5/distance"]
    assert src.clock_offset == pytest.approx(OFFSET, abs=0.06)
    assert src.start_time == pytest.approx(2000.0 + src.clock_offset)
    assert src.duration == pytest.approx(2.98, abs=0.01)
    assert src.name == f"bag_{storage}"


def test_synthetic_routes_and_frames(synthetic_bag: Path) -> None:
    events = list(RosbagSource(synthetic_bag, synthetic_team()))
    ranges = [e for e in events if isinstance(e, RangeEvent)]
    assert {(r.robot_a, r.robot_b, r.node_a, r.node_b) for r in ranges} == {
        ("r2", "r1", "n_2", "n_1")
    }
    assert all(r.node_pair == "n_1-n_2" and r.distance > 0 for r in ranges)
    dets = [e for e in events if isinstance(e, DetectionEvent)]
    assert {d.robot for d in dets} == {"r1"}
    assert all(len(d.objects) == 1 for d in dets)
    obj = dets[0].objects[0]
    assert (obj.label, obj.x, obj.y) == ("56", pytest.approx(2.1), pytest.approx(-0.2))
    gts = {e.robot for e in events if isinstance(e, GroundTruthEvent)}
    assert gts == {"r1", "r2"}


def test_zero_stamps_get_receive_time_plus_offset_of_their_kind(synthetic_bag: Path) -> None:
    src = RosbagSource(synthetic_bag, synthetic_team())
    assert src.zero_stamp_topics == {"/r2/odom"}
    events = list(src)
    r1 = [e.t for e in events if isinstance(e, OdometryEvent) and e.robot == "r1"]
    r2 = [e.t for e in events if isinstance(e, OdometryEvent) and e.robot == "r2"]
    # r2 is received 1 ms after r1; both get odometry's own lag (0.05 s), not the mocap's
    assert [b - a for a, b in zip(r1, r2, strict=True)] == pytest.approx([0.001] * 60, abs=1e-4)
    assert src.stats.restamped == {"/r2/odom": 60}


def test_forced_receive_time_and_configured_offset(synthetic_bag: Path) -> None:
    cfg = synthetic_team(clock_offset=-999.0).with_robot("r1", odom_zero_stamps=True)
    src = RosbagSource(synthetic_bag, cfg)
    assert src.clock_offset == -999.0
    odom = [e for e in src if isinstance(e, OdometryEvent) and e.robot == "r1"]
    assert odom[0].t == pytest.approx(2000.01 - 999.0)


def test_small_max_lag_drops_late_events_and_keeps_order(synthetic_bag: Path) -> None:
    src = RosbagSource(synthetic_bag, synthetic_team(), max_lag=0.05)
    events = list(src)
    assert _times(events) == sorted(_times(events))
    assert src.stats.rejected["late"] > 0  # detections are stamped 0.3 s before reception
    with pytest.raises(ValueError):
        RosbagSource(synthetic_bag, synthetic_team(), max_lag=0.0)


def test_iteration_streams_and_restarts(synthetic_bag: Path) -> None:
    src = RosbagSource(synthetic_bag, synthetic_team())
    it = iter(src)
    first = next(it)
    # the first event leaves the reorder buffer once reception is max_lag (1 s) past it:
    # about a third of this 3 s, 770-message bag has been read, not all of it
    assert sum(src.stats.messages.values()) < 200
    rest = list(it)
    again = list(src)
    assert [first, *rest] == again


def test_switches_select_kinds(synthetic_bag: Path) -> None:
    src = RosbagSource(
        synthetic_bag, synthetic_team(), ground_truth=False, detections=False, ranges=False
    )
    assert set(src.topics.values()) == {"odometry"}
    assert {type(e) for e in src} == {OdometryEvent}
    objects = RosbagSource(synthetic_bag, synthetic_team(), objects=["b2"], ground_truth=False)
    gts = {e.robot for e in objects if isinstance(e, GroundTruthEvent)}
    assert gts == {"b2"}


def test_missing_topic_lists_the_bag_topics(synthetic_bag: Path) -> None:
    cfg = synthetic_team().with_robot("r2", odom_topic="/r2/odometry")
    with pytest.raises(BagError) as info:
        RosbagSource(synthetic_bag, cfg)
    text = str(info.value)
    assert "'/r2/odometry'" in text and "odometry of r2" in text
    for topic in ("/r1/odom", "/r2/odom", "/uwb/tof/n_2/n_1/distance", "/r1/det"):
        assert topic in text
    # not required when switched off
    RosbagSource(
        synthetic_bag, synthetic_team().with_robot("r1", mocap_body="nobody"), ground_truth=False
    )


def test_wrong_types_and_templates_are_bag_errors(synthetic_bag: Path) -> None:
    with pytest.raises(BagError, match="expected geometry_msgs/msg/PoseArray"):
        RosbagSource(synthetic_bag, synthetic_team().with_robot("r1", detection_format="posearray"))
    with pytest.raises(BagError, match="expected nav_msgs/msg/Odometry"):
        RosbagSource(synthetic_bag, synthetic_team().with_robot("r1", odom_topic="/r1/det"))
    cfg = synthetic_team()
    bad_uwb = TeamConfig(
        robots=cfg.robots,
        reference="r2",
        uwb=type(cfg.uwb)(range_topic="/uwb/{a}/distance"),
    )
    with pytest.raises(BagError, match=r"\{a\} and \{b\}"):
        RosbagSource(synthetic_bag, bad_uwb)


def test_path_errors(tmp_path: Path, synthetic_bag: Path) -> None:
    cfg = synthetic_team()
    with pytest.raises(BagError, match="bag not found"):
        RosbagSource(tmp_path / "nope", cfg)
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match=r"no metadata\.yaml"):
        RosbagSource(tmp_path / "empty", cfg)
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(BagError, match="not a rosbag2 bag"):
        RosbagSource(text, cfg)
    fake = tmp_path / "fake.db3"
    fake.write_bytes(b"SQLite format 3\x00" + bytes(200))
    with pytest.raises(BagError):
        RosbagSource(fake, cfg)
    # the storage file alone is a bag too
    (db3,) = synthetic_bag.glob("*.db3")
    assert sum(1 for _ in RosbagSource(db3, cfg)) == 478


def test_undecodable_messages_are_counted(synthetic_bag: Path) -> None:
    (db3,) = synthetic_bag.glob("*.db3")
    with sqlite3.connect(db3) as db:
        db.execute(
            "UPDATE messages SET data = ? WHERE id IN (SELECT messages.id FROM messages "
            "JOIN topics ON topics.id = messages.topic_id WHERE topics.name = '/r1/odom' LIMIT 4)",
            (b"\x00\x01\x00\x00garbage!",),
        )
    db.close()
    src = RosbagSource(synthetic_bag, synthetic_team())
    events = list(src)
    assert src.stats.rejected["decode_error"] == 4
    assert sum(isinstance(e, OdometryEvent) and e.robot == "r1" for e in events) == 56


# ---------------------------------------------------------------------------- shared TIERS bags
@pytest.fixture(scope="module")
def shortbag(shared_data: Path) -> tuple[RosbagSource, list[Event]]:
    cfg = TeamConfig.load(CONFIGS / "multi4_shortbag_20221011.toml")
    src = RosbagSource(shared_data / "tiers" / "multi4_shortbag_20221011", cfg)
    return src, list(src)


@pytest.mark.shared_data
def test_shortbag_events_time_ordered_with_right_robots(
    shortbag: tuple[RosbagSource, list[Event]],
) -> None:
    src, events = shortbag
    assert _times(events) == sorted(_times(events))
    team = {"turtle01", "turtle03", "turtle04", "turtle05"}
    by_kind: dict[type, set[str]] = {}
    for e in events:
        who = {e.robot_a, e.robot_b} if isinstance(e, RangeEvent) else {e.robot}  # type: ignore[union-attr]
        by_kind.setdefault(type(e), set()).update(who)
    assert by_kind == {
        k: team for k in (OdometryEvent, RangeEvent, DetectionEvent, GroundTruthEvent)
    }
    pairs = Counter(e.node_pair for e in events if isinstance(e, RangeEvent))
    assert set(pairs) == {"n_3-n_4", "n_3-n_5", "n_3-n_7", "n_4-n_5", "n_4-n_7", "n_5-n_7"}
    assert pairs["n_3-n_4"] == 252  # reported twice as often as the others
    assert all(p.startswith("/uwb/tof/") for p in src.ignored_range_topics)
    assert len(src.ignored_range_topics) == 22  # every pair involving a static anchor
    assert src.stats.events["detection"] == 1370
    assert src.stats.rejected["detection_zero_position"] == 80
    assert src.warnings == []


@pytest.mark.shared_data
def test_shortbag_clock_offset_and_zero_stamps(shortbag: tuple[RosbagSource, list[Event]]) -> None:
    src, events = shortbag
    assert src.clock_offset == pytest.approx(-4160411.02, abs=0.05)  # 48.153 days
    assert src.duration == pytest.approx(17.2, abs=0.05)
    assert src.zero_stamp_topics == {"/cali/turtle05/odom"}
    assert src.stats.restamped == {"/cali/turtle05/odom": 338}
    odom05 = [e.t for e in events if isinstance(e, OdometryEvent) and e.robot == "turtle05"]
    odom03 = [e.t for e in events if isinstance(e, OdometryEvent) and e.robot == "turtle03"]
    assert len(odom05) == 338
    assert src.start_time <= odom05[0] < src.start_time + 0.2
    assert abs(odom05[0] - odom03[0]) < 0.1  # both started together
    odom04 = [e.t for e in events if isinstance(e, OdometryEvent) and e.robot == "turtle04"]
    assert odom04[0] - src.start_time == pytest.approx(8.4, abs=0.1)


@pytest.mark.shared_data
@pytest.mark.parametrize(
    "folder",
    [
        "multi4_shortbag_20221011",
        "pair_range_20220907_1725",
        "pair_chair_moving_20220923",
        "pair_chair_camera_noUWB_20220923",
    ],
)
def test_every_tiers_config_opens_its_bag(shared_data: Path, folder: str) -> None:
    cfg = TeamConfig.load(CONFIGS / f"{folder}.toml")
    assert cfg.name == folder
    src = RosbagSource(shared_data / "tiers" / folder, cfg)
    assert set(src.topics.values()) >= {"odometry", "ground_truth", "detection"}
    if folder.endswith("noUWB_20220923"):
        assert "range" not in src.topics.values()
        assert any("no UWB range topic" in w for w in src.warnings)
    else:
        assert "range" in src.topics.values()


@pytest.mark.shared_data
def test_pair_range_posearray_detections(shared_data: Path) -> None:
    cfg = TeamConfig.load(CONFIGS / "pair_range_20220907_1725.toml")
    src = RosbagSource(shared_data / "tiers" / "pair_range_20220907_1725", cfg, ground_truth=False)
    events = list(src)
    assert _times(events) == sorted(_times(events))
    dets = [e for e in events if isinstance(e, DetectionEvent)]
    objects = [o for d in dets for o in d.objects]
    assert len(dets) == 1710 and len(objects) == 357
    assert {o.label for o in objects} == {""}
    assert all(0.5 < o.x < 5.5 for o in objects)  # forward of the robot
    ranges = [e for e in events if isinstance(e, RangeEvent)]
    assert len(ranges) == 3357 and {r.node_pair for r in ranges} == {"n_2-n_3"}


def _copy_bag(shared_data: Path, tmp_path: Path, folder: str) -> Path:
    dst = tmp_path / folder
    shutil.copytree(shared_data / "tiers" / folder, dst)
    for f in dst.iterdir():
        f.chmod(0o644)
    return dst


@pytest.mark.shared_data
@pytest.mark.parametrize("damage", ["truncate", "garble"])
def test_damaged_bag_is_read_as_far_as_readable(
    shared_data: Path, tmp_path: Path, damage: str
) -> None:
    folder = "pair_chair_moving_20220923"
    bag = _copy_bag(shared_data, tmp_path, folder)
    (db3,) = bag.glob("*.db3")
    size = db3.stat().st_size
    if damage == "truncate":
        with db3.open("r+b") as fh:
            fh.truncate(size // 2)
    else:
        with db3.open("r+b") as fh:
            fh.seek(size // 3)
            fh.write(bytes(range(256)) * 400)
    cfg = TeamConfig.load(CONFIGS / f"{folder}.toml")
    if damage == "truncate":  # sqlite reads no message row of the half file: nothing to salvage
        with pytest.raises(BagError, match="corrupted or truncated"):
            list(RosbagSource(bag, cfg))
        return
    # garbled pages: the rows before them are read, with a warning that says how much was lost
    source = RosbagSource(bag, cfg)
    events = list(source)
    assert source.warnings[-1].endswith(
        "3230 of its 8923 messages readable, 5693 (64 %) lost; reading what is readable"
    )
    assert len(events) == 2476 and source.stats.rejected["bag_damaged"] == 1


@pytest.mark.parametrize(
    "text",
    [
        "this: is: [not yaml\n\x00\xff",
        "a: [1, 2\n",
        "rosbag2_bagfile_information:\n  version: 5\n",
        "42\n",
    ],
)
def test_garbage_metadata_is_a_bag_error_naming_the_file(tmp_path: Path, text: str) -> None:
    (tmp_path / "metadata.yaml").write_bytes(text.encode("latin-1"))
    with pytest.raises(BagError, match=r"its metadata\.yaml is not rosbag2 metadata") as info:
        RosbagSource(tmp_path, TeamConfig.load(CONFIGS / "multi4_shortbag_20221011.toml"))
    assert "\n" not in str(info.value)


@pytest.mark.shared_data
def test_real_bag_missing_topic_lists_topics(shared_data: Path) -> None:
    cfg = TeamConfig.load(CONFIGS / "pair_chair_moving_20220923.toml")
    cfg = cfg.with_robot("turtle01", odom_topic="/cali/turtle01/odom")
    with pytest.raises(BagError) as info:
        RosbagSource(shared_data / "tiers" / "pair_chair_moving_20220923", cfg)
    assert "/cali/turtle01/odom" in str(info.value)
    assert "/uwb/tof/n_7/n_3/distance  [sensor_msgs/msg/Range, 252 msgs]" in str(info.value)


def test_replay_start_outside_the_bag_is_a_clear_error(synthetic_bag: Path) -> None:
    """``relloc replay --start`` past the end would replay nothing and exit 0: refused."""
    from relloc.live.publish import ReplayOptions, replay_bag

    with pytest.raises(BagError, match="outside"):
        replay_bag(synthetic_bag, synthetic_team(), None, ReplayOptions(start=1e9, wait=0.0))


def _fingerprint(events: list[Event]) -> tuple[dict[str, int], str]:
    """Events per type and a SHA-256 (first 16 hex digits) of the sequence of (type, robot,
    stamp) as Python writes them: any change of order, stamp or routing changes it."""
    digest = hashlib.sha256()
    for e in events:
        who = f"{e.robot_a}-{e.robot_b}" if isinstance(e, RangeEvent) else e.robot  # type: ignore[union-attr]
        digest.update(f"{type(e).__name__}|{who}|{e.t!r};".encode())
    return dict(Counter(type(e).__name__ for e in events)), digest.hexdigest()[:16]


@pytest.mark.shared_data
def test_shortbag_event_sequence_is_the_reference(
    shortbag: tuple[RosbagSource, list[Event]],
) -> None:
    """The shortbag's events, their order and their stamps, recorded before the sources shared
    one ingestion layer (commit 96b88d6): the refactor must give exactly these."""
    src, events = shortbag
    counts, digest = _fingerprint(events)
    assert counts == {
        "GroundTruthEvent": 4122,
        "OdometryEvent": 1194,
        "RangeEvent": 880,
        "DetectionEvent": 1370,
    }
    assert digest == "5cbf2c800fcd40ef"
    assert math.fsum(e.distance for e in events if isinstance(e, RangeEvent)) == pytest.approx(
        4192.4300129413605, abs=1e-9
    )
    assert src.stats.repeated_ranges == 111
    assert src.stats.rejected == {"detection_zero_position": 80}
