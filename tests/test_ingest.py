"""The shared ingestion layer: routes from the team config, message-to-event conversion, the
header clock, the reorder buffer and the stats record, without any transport; and the ranging
CSV export, which reads a bag through the same layer.
"""

from __future__ import annotations

import hashlib
import logging
import math
from pathlib import Path

import pytest

from relloc.config import CameraConfig, ConfigError, RobotConfig, TeamConfig, UwbConfig
from relloc.events import DetectionEvent, GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.ros.messages import (
    ODOMETRY,
    POSE_ARRAY,
    POSE_STAMPED,
    SPATIAL_DETECTION_ARRAY,
    decode,
    encode,
    odometry_msg,
    odometry_to_event,
    quaternion_from_yaw,
    range_msg,
    time_msg,
    typestore,
)
from relloc.sensors import Route
from relloc.sources.clock import HeaderClock
from relloc.sources.ingest import (
    Converter,
    IngestStats,
    event_kind,
    match_range_topics,
    team_routes,
)
from relloc.sources.reorder import ReorderBuffer

T0 = 1_700_000_000.0


def team(**changes: object) -> TeamConfig:
    robots = (
        RobotConfig("a", uwb_node="n_1", odom_topic="/a/odom", mocap_body="body_a"),
        RobotConfig(
            "b",
            uwb_node="n_2",
            odom_topic="/b/odom",
            detection_topic="/b/dets",
            detection_format="posearray",
            camera=CameraConfig(x=0.1),
        ),
        RobotConfig("c", uwb_node="n_3", odom_topic="/c/odom", odom_zero_stamps=True),
        RobotConfig("d", odom_topic="/d/odom", detection_topic="/d/dets"),
    )
    return TeamConfig(robots=robots, reference="a", **changes)  # type: ignore[arg-type]


def route_of(routes: list[Route], topic: str) -> Route:
    (route,) = [r for r in routes if r.topic == topic]
    return route


# ---------------------------------------------------------------------------- routes
def test_team_routes_per_robot_then_objects_then_both_orders_of_every_pair() -> None:
    routes = team_routes(team(), ground_truth=True, objects=["chair"])
    assert [(r.kind, r.robot) for r in routes[:8]] == [
        ("odometry", "a"),
        ("ground_truth", "a"),
        ("odometry", "b"),
        ("detection", "b"),
        ("odometry", "c"),
        ("odometry", "d"),
        ("detection", "d"),
        ("ground_truth", "chair"),
    ]
    assert [r.topic for r in routes[8:]] == [
        f"/uwb/tof/{a}/{b}/distance"
        for a, b in (
            ("n_1", "n_2"),
            ("n_2", "n_1"),
            ("n_1", "n_3"),
            ("n_3", "n_1"),
            ("n_2", "n_3"),
            ("n_3", "n_2"),
        )
    ]
    r = route_of(routes, "/uwb/tof/n_3/n_2/distance")
    assert (r.robot, r.robot_b, r.node_a, r.node_b, r.what) == (
        "c",
        "b",
        "n_3",
        "n_2",
        "UWB ranges n_3-n_2",
    )
    assert route_of(routes, "/vrpn_client_node/body_a/pose").what == "motion capture of a"
    assert route_of(routes, "/vrpn_client_node/chair/pose").what == "motion capture of object chair"
    assert route_of(routes, "/c/odom").zero_stamps and not route_of(routes, "/a/odom").zero_stamps
    assert route_of(routes, "/b/dets").msgtypes == (POSE_ARRAY,)
    assert route_of(routes, "/d/dets").msgtypes == (SPATIAL_DETECTION_ARRAY, POSE_ARRAY)
    assert route_of(routes, "/b/dets").camera == CameraConfig(x=0.1)


def test_team_routes_switches_and_template_check() -> None:
    only_odom = team_routes(team(), ranges=False, detections=False)
    assert {r.kind for r in only_odom} == {"odometry"} and len(only_odom) == 4
    assert not any(r.kind == "ground_truth" for r in team_routes(team()))  # off unless asked
    bad = team(uwb=UwbConfig(range_topic="/uwb/{a}/distance"))
    with pytest.raises(ConfigError, match=r"\{a\} and \{b\}"):
        team_routes(bad)
    assert len(team_routes(bad, ranges=False)) == 6


def test_match_range_topics_finds_every_node_pair_anchors_too() -> None:
    topics = [
        "/uwb/tof/n_2/n_1/distance",
        "/uwb/tof/n_1/a_9/distance",
        "/uwb/tof/n_1/distance",
        "/a/odom",
        "/uwb/tof/n_1/n_2/distance/extra",
    ]
    assert match_range_topics(topics, "/uwb/tof/{a}/{b}/distance") == {
        "/uwb/tof/n_1/a_9/distance": ("n_1", "a_9"),
        "/uwb/tof/n_2/n_1/distance": ("n_2", "n_1"),
    }
    with pytest.raises(ConfigError):
        match_range_topics(topics, "/uwb/{a}")


# ---------------------------------------------------------------------------- conversion
def _converter(**clock: object) -> tuple[Converter, IngestStats]:
    stats = IngestStats()
    return Converter(stats, HeaderClock(**clock)), stats  # type: ignore[arg-type]


def odom(robot: str, t: float) -> bytes:
    return encode(odometry_msg(OdometryEvent(t, robot, 0.0, 2.0, 0.3)))


def test_odometry_fast_path_gives_the_full_decoders_event() -> None:
    route = route_of(team_routes(team()), "/a/odom")
    convert, stats = _converter()
    for little_endian in (True, False):
        msg = odometry_msg(OdometryEvent(T0 + 0.25, "a", 1.5, 2.0, 0.3, v=0.5, w=-0.1))
        payload = bytes(typestore().serialize_cdr(msg, ODOMETRY, little_endian=little_endian))
        event = convert.convert(route, "/a/odom", payload, T0 + 0.3)
        assert event == odometry_to_event(decode(payload, ODOMETRY), "a")
        assert (event.t, event.x, event.v) == (T0 + 0.25, 1.5, 0.5)
        assert event.yaw == pytest.approx(0.3, abs=1e-12)
    assert stats.messages == {"/a/odom": 2} and stats.last_received == {"a": T0 + 0.3}


def test_ranges_rejected_repeated_and_counted() -> None:
    route = route_of(team_routes(team()), "/uwb/tof/n_2/n_1/distance")
    convert, stats = _converter()
    out = []
    for k, d in enumerate([3.0, math.nan, -1.0, 0.0, 3.0, 3.0, 2.5]):
        ev = convert.convert(route, "k", encode(range_msg(RangeEvent(T0 + k, "", "", d))), T0 + k)
        out.append(ev)
    kept = [e for e in out if e is not None]
    assert [e.distance for e in kept] == [3.0, 3.0, 3.0, 2.5]
    assert {(e.robot_a, e.robot_b, e.node_a, e.node_b) for e in kept} == {("b", "a", "n_2", "n_1")}
    assert stats.rejected == {"range_nonfinite": 1, "range_nonpositive": 2}
    assert stats.repeated_ranges == 2  # 3.0 after 3.0, twice; a rejected value does not count
    assert stats.last_received == {"b": T0 + 6, "a": T0 + 6}


def test_undecodable_payload_tries_every_type_counts_and_logs(
    caplog: pytest.LogCaptureFixture,
) -> None:
    route = route_of(team_routes(team()), "/d/dets")
    stats = IngestStats()
    convert = Converter(stats, HeaderClock(), logging.getLogger("test_ingest"))
    with caplog.at_level(logging.WARNING, logger="test_ingest"):
        for _ in range(3):
            assert convert.convert(route, "d/dets", b"\x00\x01\x00\x00garbage", T0) is None
    assert stats.rejected == {"decode_error": 3}
    assert len(caplog.records) == 1 and "decode_error" in caplog.records[0].getMessage()
    quiet, quiet_stats = _converter()
    quiet.convert(route, "d/dets", b"", T0)
    assert quiet_stats.rejected == {"decode_error": 1}


def test_detections_and_ground_truth() -> None:
    types = typestore().types

    def pose(x: float, y: float, z: float):
        return types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
            orientation=quaternion_from_yaw(0.0),
        )

    header = types["std_msgs/msg/Header"](stamp=time_msg(T0), frame_id="cam")
    frame = types[POSE_ARRAY](header=header, poses=[pose(0.5, 0.0, 2.0), pose(0.0, 0.0, 0.0)])
    routes = team_routes(team(), ground_truth=True)
    convert, stats = _converter()
    det = convert.convert(route_of(routes, "/b/dets"), "/b/dets", encode(frame), T0 + 0.3)
    assert isinstance(det, DetectionEvent) and det.t == T0 and det.robot == "b"
    (obj,) = det.objects
    assert (obj.x, obj.y) == (pytest.approx(2.1), pytest.approx(-0.5))  # optical -> body, +0.1
    assert stats.rejected == {"detection_zero_position": 1}
    mocap = types[POSE_STAMPED](header=header, pose=pose(1.0, 2.0, 0.1))
    gt = convert.convert(route_of(routes, "/vrpn_client_node/body_a/pose"), "m", encode(mocap), T0)
    assert gt == GroundTruthEvent(T0, "a", (1.0, 2.0), 0.0)


def test_zero_stamps_take_the_receive_time_on_their_kinds_clock_and_keep_increasing() -> None:
    routes = team_routes(team())
    convert, stats = _converter(rate=2.0)
    for k in range(5):  # a's odometry: header = 2 * wall - 1000 (replayed at 2x)
        wall = 100.0 + 0.05 * k
        convert.convert(route_of(routes, "/a/odom"), "a/odom", odom("a", 2 * wall - 1000.0), wall)
    b_zero = convert.convert(route_of(routes, "/b/odom"), "b/odom", odom("b", 0.0), 100.5)
    c1 = convert.convert(route_of(routes, "/c/odom"), "c/odom", odom("c", 5.0), 100.5)
    c2 = convert.convert(route_of(routes, "/c/odom"), "c/odom", odom("c", 6.0), 100.5)
    assert b_zero is not None and c1 is not None and c2 is not None
    assert b_zero.t == pytest.approx(2 * 100.5 - 1000.0)
    # c is flagged odom_zero_stamps: its own stamps (5, 6) are ignored; same arrival, +1 us
    assert c1.t == pytest.approx(2 * 100.5 - 1000.0) and c2.t == c1.t + 1e-6
    assert stats.restamped == {"b/odom": 1, "c/odom": 2}


# ---------------------------------------------------------------------------- clock
def test_clock_offset_is_the_median_of_each_streams_median_per_kind() -> None:
    clock = HeaderClock()
    assert clock.stamp("odometry", 12.0) == 12.0  # nothing seen: the receive clock itself
    # the shortbag's situation: one constant offset, a kind-specific lag on top of it
    big = -4_160_411.0
    for k in range(50):
        recv = 100.0 + 0.1 * k
        clock.observe("/uwb/1", "range", recv + big, recv)
        clock.observe("/odom/1", "odometry", recv + big - 0.03, recv)
        clock.observe("/odom/2", "odometry", recv + big - 0.05, recv)
        clock.observe("/odom/3", "odometry", recv + big - (0.04 if k % 10 else 9.0), recv)
        clock.observe("/odom/zero", "odometry", 0.0, recv)
    assert clock.offset("odometry") == pytest.approx(big - 0.04, abs=1e-6)  # outliers ignored
    assert clock.offset("range") == pytest.approx(big, abs=1e-6)
    assert clock.offset("detection") == pytest.approx(big - 0.035, abs=1e-6)  # over all streams
    assert clock.overall == clock.offset("detection")
    assert clock.stamp("range", 200.0) == pytest.approx(200.0 + big, abs=1e-6)
    assert clock.zero_stamp_streams == {"/odom/zero"}
    assert clock.seen("/odom/zero") == 50 and clock.seen("/uwb/1") == 50
    assert list(clock.stream_offsets()) == ["/uwb/1", "/odom/1", "/odom/2", "/odom/3"]


def test_clock_window_freeze_and_fixed_offset() -> None:
    clock = HeaderClock(rate=2.0, window=3)
    for k in range(1, 7):  # the offset drifts; only the last three count
        clock.observe("s", "range", 2.0 * k + 10.0 * k, float(k))
    assert clock.offset("range") == 50.0  # median of 40, 50, 60
    clock.freeze()
    clock.observe("s", "range", 1e9, 7.0)
    assert clock.offset("range") == 50.0 and clock.seen("s") == 3
    assert HeaderClock(fixed_offset=-3.0).stamp("range", 10.0) == 7.0
    with pytest.raises(ValueError):
        HeaderClock(rate=0.0)


# ---------------------------------------------------------------------------- reorder buffer
def test_reorder_buffer_releases_in_stamp_order_within_its_window() -> None:
    buf: ReorderBuffer[float] = ReorderBuffer(0.2, hold=0.2)

    def push(t: float, received: float) -> None:
        buf.push(t, t, received)
        buf.advance(t)

    for t in (10.00, 10.10, 10.05, 10.15):
        push(t, received=100.0)
    assert buf.pop_ready(100.01) == []  # nothing is 0.2 s behind the newest yet
    push(10.30, received=100.02)
    assert buf.pop_ready(100.02) == [10.00, 10.05, 10.10]
    assert buf.next_due() == pytest.approx(100.2)
    # the rest leaves once it has waited the hold (a quiet team is not held back)
    assert buf.pop_ready(100.21) == [10.15]
    assert buf.pop_ready(100.23) == [10.30]
    # later than the window: passed on at once, counted; the localizer judges it
    push(10.12, received=100.3)
    assert buf.pop_ready(100.3) == [10.12]
    assert buf.late == 1 and buf.max_depth == 5 and len(buf) == 0


def test_reorder_buffer_zero_window_ties_and_flush() -> None:
    buf: ReorderBuffer[str] = ReorderBuffer(0.0)
    buf.push(5.0, "five")
    buf.push(4.0, "four")
    buf.push(4.0, "four again")  # equal stamps leave in push order
    assert buf.pop_ready() == []  # not advanced: nothing known to have arrived
    buf.advance(5.0)
    assert buf.pop_ready() == ["four", "four again", "five"]
    buf.push(3.0, "three")
    buf.push(6.0, "six")
    assert buf.flush() == ["three", "six"] and buf.late == 1
    with pytest.raises(ValueError):
        ReorderBuffer(-0.1)


def test_reorder_buffer_advanced_by_receive_time_drops_late_items() -> None:
    """The bag's use: advanced by receive time on the header clock, late items dropped."""
    buf: ReorderBuffer[float] = ReorderBuffer(1.0, drop_late=True)
    released: list[float] = []
    # (stamp, receive time on the header clock): 0.4 arrives 2 s late, after 0.5 has left
    for t, now in ((0.0, 0.1), (0.5, 0.6), (2.0, 2.1), (0.4, 2.4), (2.2, 2.5)):
        buf.push(t, t)
        buf.advance(now)
        released += buf.pop_ready()
    released += buf.flush()
    assert released == [0.0, 0.5, 2.0, 2.2]
    assert buf.late == 1


# ---------------------------------------------------------------------------- stats
def test_stats_record_counts_emitted_kinds_and_has_one_plain_view() -> None:
    stats = IngestStats(clock_offset=-2.5)
    for event in (
        OdometryEvent(0.0, "a", 0.0, 0.0, 0.0),
        OdometryEvent(0.1, "a", 0.0, 0.0, 0.0),
        RangeEvent(0.1, "a", "b", 3.0),
        DetectionEvent(0.2, "b"),
        GroundTruthEvent(0.3, "a", (0.0, 0.0)),
    ):
        stats.emitted(event)
    stats.rejected["late"] += 1
    assert stats.as_dict() == {
        "messages": {},
        "events": {"odometry": 2, "range": 1, "detection": 1, "ground_truth": 1},
        "rejected": {"late": 1},
        "restamped": {},
        "repeated_ranges": 0,
        "layouts": {},
        "out_of_order": 0,
        "clock_offset": -2.5,
    }
    assert event_kind(RangeEvent(0.0, "a", "b", 1.0)) == "range"


# ---------------------------------------------------------------------------- ranging CSV
@pytest.mark.shared_data
def test_bag_csv_rows_are_the_reference(shared_data: Path) -> None:
    """The rows of ``relloc ranging bag-csv`` on the chair recording, recorded when it still
    had its own bag reader (commit 96b88d6): reading through RosbagSource gives the same."""
    from relloc.evaluation.range_errors import bag_rows, parse_bodies

    bodies = parse_bodies("n_7=turtlebot1_cap,n_3=turtlebot3_cap")
    rows = bag_rows(shared_data / "tiers" / "pair_chair_moving_20220923", bodies)
    assert len(rows) == 252
    assert hashlib.sha256(repr(rows).encode()).hexdigest()[:16] == "3ab31a17e97fc186"
    assert {(r[1], r[2]) for r in rows} == {("n_7", "n_3")}


def test_bag_csv_errors(tmp_path: Path) -> None:
    from relloc.evaluation.range_errors import bag_rows
    from relloc.ranging.dataset import RangingDataError

    with pytest.raises(RangingDataError, match="bag not found"):
        bag_rows(tmp_path / "nope", {"n_1": "a", "n_2": "b"})
    with pytest.raises(RangingDataError, match="fewer than two"):
        bag_rows(tmp_path / "nope", {"n_1": "a"})
