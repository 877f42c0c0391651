"""The live Zenoh source without a network: keys, decoding, rejections, ordering, clocks, and a
robot that goes quiet for 5 s (on a simulated clock).

Messages enter through ``ZenohSource.handle(key, payload, received)`` (what the Zenoh callback
feeds the engine thread) with explicit receive times, so every test is deterministic.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from relloc.config import ConfigError, RobotConfig, TeamConfig
from relloc.events import OdometryEvent, RangeEvent
from relloc.live import LiveServer, ServeOptions, event_messages, simulated_team
from relloc.ros.interfaces import decode_sent_time, encode_sent_time, key_for_topic
from relloc.ros.messages import encode, odometry_msg, range_msg
from relloc.sources.zenoh_keys import build_routes
from relloc.sources.zenoh_source import ZenohSource, ZenohSourceOptions

T0 = 1_700_000_000.0
CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "tiers"


def team(**robot_changes: Any) -> TeamConfig:
    """Three robots; ``robot_changes`` apply to robot ``c``."""
    robots = (
        RobotConfig("a", uwb_node="n_1", odom_topic="/a/odom"),
        RobotConfig("b", uwb_node="n_2", odom_topic="/b/odom", detection_topic="/b/dets"),
        RobotConfig("c", **{"uwb_node": "n_3", "odom_topic": "/c/odom", **robot_changes}),
    )
    return TeamConfig(robots=robots, reference="a")


def odom_payload(robot: str, t: float, x: float = 0.0) -> bytes:
    return encode(odometry_msg(OdometryEvent(t, robot, x, 0.0, 0.0)))


def range_payload(t: float, d: float) -> bytes:
    return encode(range_msg(RangeEvent(t, "a", "b", d)))


class _Nothing:
    """Stands in for a Zenoh session/publisher/subscriber where nothing must go on the wire."""

    def declare_publisher(self, key: str) -> _Nothing:
        return self

    def declare_subscriber(self, key: str, callback: Any) -> _Nothing:
        return self

    def put(self, payload: bytes, **kwargs: Any) -> None:
        pass

    def undeclare(self) -> None:
        pass


# ---------------------------------------------------------------------------- keys
def test_keys_follow_the_bridge_convention_with_scopes_and_prefix() -> None:
    assert key_for_topic("/tb1/odom") == "tb1/odom"
    assert key_for_topic("/odom", prefix="lab/", scope="tb1") == "lab/tb1/odom"
    with pytest.raises(ConfigError):
        key_for_topic("/a/*/odom")

    routes = build_routes(team(zenoh_scope="tbc"), prefix="lab")
    assert routes["lab/a/odom"].robot == "a"
    assert routes["lab/tbc/c/odom"].kind == "odometry"
    # every pair, both node orders; a pair with a scoped robot also below its scope
    r = routes["lab/uwb/tof/n_3/n_1/distance"]
    assert (r.robot, r.robot_b, r.node_a, r.node_b) == ("c", "a", "n_3", "n_1")
    assert "lab/tbc/uwb/tof/n_1/n_3/distance" in routes
    assert "lab/tbc/uwb/tof/n_1/n_2/distance" not in routes
    assert len([k for k, v in routes.items() if v.kind == "range"]) == 2 * 3 + 2 * 2
    assert routes["lab/b/dets"].kind == "detection"
    assert "lab/b/dets" not in build_routes(team(), prefix="lab", detections=False)


def test_two_robots_on_one_key_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="zenoh_scope"):
        build_routes(team(odom_topic="/a/odom"))


def test_sent_time_attachment_round_trips() -> None:
    assert decode_sent_time(encode_sent_time(T0 + 0.25)) == T0 + 0.25
    assert decode_sent_time(b"something else") is None
    assert decode_sent_time(None) is None


# ---------------------------------------------------------------------------- rejections
def test_malformed_payloads_are_rejected_counted_and_do_not_stop_the_source() -> None:
    src = ZenohSource(team())
    good = odom_payload("a", T0)
    src.handle("a/odom", b"\x00\x01\x00\x00garbage", T0)
    src.handle("a/odom", good[: len(good) // 2], T0)  # truncated
    src.handle("uwb/tof/n_1/n_2/distance", good, T0)  # an Odometry where a Range belongs
    src.handle("a/odom", b"", T0)
    assert src.stats.rejected["decode_error"] == 4
    src.handle("a/odom", good, T0 + 0.1)
    src.handle("a/odom", memoryview(odom_payload("a", T0 + 0.2)), T0 + 0.2)  # other transports
    src.handle("a/odom", bytearray(odom_payload("a", T0 + 0.3)), T0 + 0.3)
    out = src.flush()
    assert [type(a.event) for a in out] == [OdometryEvent] * 3
    assert src.stats.events == {"odometry": 3}


def test_unknown_keys_and_bad_values_are_counted() -> None:
    src = ZenohSource(team())
    src.handle("someone/else/odom", odom_payload("a", T0), T0)
    src.handle("uwb/tof/n_1/n_2/distance", range_payload(T0, math.nan), T0)
    src.handle("uwb/tof/n_1/n_2/distance", range_payload(T0, -1.0), T0)
    assert src.stats.rejected == {"unknown_key": 1, "range_nonfinite": 1, "range_nonpositive": 1}
    assert src.flush() == []


def test_detections_decode_in_the_body_frame() -> None:
    from relloc.ros.messages import typestore

    types = typestore().types
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=2.0),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    from relloc.ros.messages import time_msg

    header = types["std_msgs/msg/Header"](stamp=time_msg(T0), frame_id="cam")
    msg = types["geometry_msgs/msg/PoseArray"](header=header, poses=[pose])
    src = ZenohSource(team())
    src.handle("b/dets", encode(msg), T0)
    (arrival,) = src.flush()
    (obj,) = arrival.event.objects
    assert arrival.event.robot == "b"
    assert obj.x == pytest.approx(2.0)  # optical z (forward) -> body x


class _Sample:
    """What the source reads from a ``zenoh.Sample``."""

    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr = key
        self.payload = _Bytes(payload)
        self.attachment = _Bytes(encode_sent_time(T0 - 1.0))


class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


def test_callback_enqueues_and_a_full_queue_drops_and_counts() -> None:
    src = ZenohSource(team(), ZenohSourceOptions(queue_size=2))
    for k in range(3):
        src.on_sample(_Sample("a/odom", odom_payload("a", T0 + k)))
    released = src.poll(timeout=0.0) + src.flush()
    assert [a.event.t for a in released] == [T0, T0 + 1]
    assert released[0].sent == T0 - 1.0
    assert src.stats.rejected == {"queue_full": 1}


# ---------------------------------------------------------------------------- ordering and clocks
def test_late_events_reach_the_localizer_which_rejects_what_is_too_late() -> None:
    """Out-of-order timestamps: reordered within the window, rejected by the localizer after."""
    server = LiveServer(team(), _Nothing(), ServeOptions(reorder_window=0.1))
    src = server.source
    src.handle("a/odom", odom_payload("a", T0 + 0.00, 0.0), 50.0)
    src.handle("a/odom", odom_payload("a", T0 + 0.10, 0.1), 50.1)
    src.handle("a/odom", odom_payload("a", T0 + 0.05, 0.05), 50.1)  # late, within the window
    src.handle("a/odom", odom_payload("a", T0 + 0.30, 0.3), 50.3)
    server.feed(src.release(50.3))
    src.handle("a/odom", odom_payload("a", T0 + 0.08, 0.08), 50.35)  # later than the window
    server.feed(src.release(50.35))
    server.feed(src.flush())
    server.engine.finish()  # five events of one robot: the team clock is set at the end
    loc = server.pipelines[0].localizer
    assert loc.stats["odometry"] == 4
    assert loc.rejected == {"out_of_order_odometry": 1}
    assert src.stats.out_of_order == 1


def test_zero_stamps_get_the_receive_time_on_the_header_clock() -> None:
    # c's odometry has zero stamps; a's are stamped 1000 s behind the wall clock, at 2x speed
    src = ZenohSource(team(odom_zero_stamps=True), ZenohSourceOptions(clock_rate=2.0))
    for k in range(5):
        wall = 100.0 + 0.05 * k
        src.handle("a/odom", odom_payload("a", 2 * wall - 1000.0), wall)
    src.handle("c/odom", odom_payload("c", 0.0), 100.5)
    src.handle("c/odom", odom_payload("c", 0.0), 100.5)  # same arrival: still increasing
    c = [a.event.t for a in src.flush() if a.event.robot == "c"]
    assert c[0] == pytest.approx(2 * 100.5 - 1000.0)
    assert c[1] > c[0]
    assert src.stats.restamped == {"c/odom": 2}


# ---------------------------------------------------------------------------- a robot goes quiet
def _quiet_run(seed: int) -> dict[str, float]:
    """Simulated 5-robot team, simulated clock, the filter seeded ``seed``: r3 publishes
    nothing from 20 s to 25 s. The figures the test bounds; what holds on every seed is
    asserted here."""
    sim, config = simulated_team(seed=0, duration=40.0)
    server = LiveServer(config, _Nothing(), ServeOptions(particles=3000, seed=seed))
    src = server.source
    quiet, gap = "r3", (20.0, 25.0)
    status: dict[float, dict[str, Any]] = {}
    nodes = {r.uwb_node: r.name for r in config.robots}
    for t, channel, payload in event_messages(sim.events(), config, time_base=T0):
        key = channel.key
        route = src.routes[key]
        involved = {route.robot, route.robot_b} if route.robot_b else {route.robot}
        assert involved <= set(nodes.values())
        if quiet in involved and gap[0] <= t < gap[1]:
            continue
        src.handle(key, payload, T0 + t)
        server.feed(src.release(T0 + t))
        for probe in (22.0, 30.0):
            if probe not in status and t >= probe:
                status[probe] = server.status(T0 + t)["robots"][quiet]
    server.feed(src.flush())
    assert status[22.0]["quiet"] and not status[30.0]["quiet"]

    def errors(lo: float, hi: float, robot: str) -> list[float]:
        out = []
        for est in server.pipelines[0].estimates:
            t = est.t - T0
            if lo <= t < hi:
                p, q = sim.true_pose(robot, t), sim.true_pose(config.reference, t)
                x, y = est.positions[robot]
                out.append(math.hypot(x - (p[0] - q[0]), y - (p[1] - q[1])))
        return out

    assert len(errors(*gap, "r1")) >= 30  # estimates keep coming at ~8 Hz while r3 is silent
    assert server.engine_errors == 0
    assert server.pipelines[0].localizer.rejected == {}
    return {
        "others": max(float(np.median(errors(*gap, other))) for other in ("r1", "r2", "r4")),
        "quiet_max": max(errors(*gap, quiet)),
        "quiet_after": float(np.median(errors(28.0, 40.0, quiet))),
    }


def test_a_robot_quiet_for_5_s_does_not_stop_the_others_and_recovers() -> None:
    """r3 silent 20-25 s (:func:`_quiet_run`), filter seeds 0-2, all but one seed within each
    bound. One seed in about ten starts in a wrong formation and stays there (its error is as
    large before the silence as during it): seeds 0-23 with the NumPy step, median error of the
    others during the gap 0.07-0.22 m, seeds 14 and 21 0.53 and 0.45 m; with the compiled step
    seed 0 1.09 m (1.18 m before the gap), the others 0.09-0.28 m."""
    runs = [_quiet_run(seed) for seed in (0, 1, 2)]

    def all_but_one(key: str, bound: float) -> bool:
        return sum(run[key] < bound for run in runs) >= len(runs) - 1

    assert all_but_one("others", 0.4), runs  # the others go on while r3 is silent
    assert all_but_one("quiet_max", 1.5), runs  # extrapolation is bounded: r3 does not drift
    assert all_but_one("quiet_after", 0.3), runs  # back once it publishes again


# ---------------------------------------------------------------------------- the bag, live
@pytest.mark.shared_data
def test_the_shortbag_fed_live_gives_the_bag_sources_events(shared_data: Path) -> None:
    """Both sources share one ingestion layer: the shortbag's messages handed to the live source
    at their receive times give RosbagSource's events (motion capture aside), except that the
    zero-stamped turtle05 odometry is restamped by a clock still learning (within 11 ms)."""
    from rosbags.rosbag2 import Reader

    from relloc.events import GroundTruthEvent
    from relloc.sources.rosbag import RosbagSource

    folder = shared_data / "tiers" / "multi4_shortbag_20221011"
    config = TeamConfig.load(CONFIGS / "multi4_shortbag_20221011.toml")
    src = ZenohSource(config, ZenohSourceOptions(reorder_window=0.2))
    topic_key = {route.topic: key for key, route in src.routes.items()}
    live = []
    with Reader(folder) as reader:
        conns = [c for c in reader.connections if c.topic in topic_key]
        for conn, recv_ns, raw in reader.messages(conns):
            src.handle(topic_key[conn.topic], raw, recv_ns * 1e-9)
            live += [a.event for a in src.release(recv_ns * 1e-9)]
    live += [a.event for a in src.flush()]
    bag = [e for e in RosbagSource(folder, config) if not isinstance(e, GroundTruthEvent)]

    def restamped(e: object) -> bool:
        return isinstance(e, OdometryEvent) and e.robot == "turtle05"

    assert sorted(map(repr, (e for e in live if not restamped(e)))) == sorted(
        map(repr, (e for e in bag if not restamped(e)))
    )
    lag = np.array([a.t for a in live if restamped(a)]) - [b.t for b in bag if restamped(b)]
    assert len(lag) == 338 and np.abs(lag).max() < 0.011
    assert src.stats.restamped == {"cali/turtle05/odom": 338}
    assert src.stats.repeated_ranges == 111
    assert src.stats.rejected == {"detection_zero_position": 80}
    assert src.stats.out_of_order == 1368  # detections come 0.3 s late, past the 0.2 s window


def test_own_outputs_are_counted_not_rejected() -> None:
    """With ``--subscribe-all`` the server receives its own poses and status: counted apart."""
    src = ZenohSource(team(), ZenohSourceOptions(own_prefix="relloc"))
    src.handle("relloc/status", b"{}", T0)
    src.handle("relloc/b/pose", b"\x00", T0)
    src.handle("someone/else/odom", odom_payload("a", T0), T0)
    assert src.own_outputs == 2 and src.stats.rejected == {"unknown_key": 1}


def test_the_server_injects_faults_and_reports_them_in_the_status() -> None:
    from relloc.faults import Faults, Window

    opts = ServeOptions(faults=Faults(drop=0.3, silence=(Window(T0 + 1.0, T0 + 2.0, "a"),), seed=1))
    server = LiveServer(team(), _Nothing(), opts)
    src = server.source
    for k in range(40):
        src.handle("a/odom", odom_payload("a", T0 + 0.1 * k, 0.01 * k), 50.0 + 0.1 * k)
    server.feed(src.flush())
    server.engine.finish()
    status = server.status()
    injected = status["injected_faults"]
    assert (
        injected["silenced"] + injected["dropped"] + server.pipelines[0].localizer.stats["odometry"]
        == 40
    )
    assert injected["silenced"] >= 5 and injected["dropped"] >= 5
    faults = status["methods"]["pf"]["faults"]
    assert faults["recovering"] is False and faults["odometry_reanchored"] == 0
    assert set(faults) >= {
        "divergence_detected",
        "clock_jumps_followed",
        "time_jump",
        "time_jump_backward",
    }


def test_one_future_stamp_does_not_disable_the_reorder_window() -> None:
    """A message stamped an hour ahead neither releases what is held nor makes later messages
    late (the buffer's time follows the header clock, not the newest stamp): the swapped
    messages after it are still put in order."""
    src = ZenohSource(team(), ZenohSourceOptions(reorder_window=0.2))
    out = []
    for k in range(20):
        src.handle("a/odom", odom_payload("a", T0 + 0.1 * k), T0 + 0.1 * k + 0.01)
        out += src.release(T0 + 0.1 * k + 0.01)
    src.handle("a/odom", odom_payload("a", T0 + 3600.0), T0 + 2.0)
    for k in range(20, 40, 2):  # each pair arrives swapped
        src.handle("a/odom", odom_payload("a", T0 + 0.1 * (k + 1)), T0 + 0.1 * k + 0.01)
        src.handle("a/odom", odom_payload("a", T0 + 0.1 * k), T0 + 0.1 * k + 0.02)
        out += src.release(T0 + 0.1 * k + 0.02)
    out += src.flush()
    stamps = [a.event.t for a in out]
    assert (
        len(stamps) == 41 and T0 + 3600.0 in stamps
    )  # let out after its hold (the localizer rejects it)
    normal = [t for t in stamps if t < T0 + 10.0]
    assert normal == sorted(normal) and src.stats.out_of_order == 0


@pytest.mark.parametrize(("hold", "late"), [(None, 1), (math.inf, 0)])
def test_an_infinite_hold_keeps_the_order_through_a_stalled_publisher(
    hold: float | None, late: int
) -> None:
    """A publisher stalled for 1 s while one of its messages waits (a replay starved of the
    GIL): with the hold on the wall clock (the window at ``clock_rate``: 0.2 s) the waiting one
    is let out and the one stamped before it, sent after the stall, is late; released by the
    stamps alone (``reorder_hold`` infinite) both come out in order."""
    src = ZenohSource(team(), ZenohSourceOptions(reorder_window=0.2, reorder_hold=hold))
    out = src.release(T0)
    src.handle("a/odom", odom_payload("a", T0 + 0.1), T0 + 0.1)
    out += src.release(T0 + 1.1)  # the stall: the engine runs, the publisher does not
    src.handle("a/odom", odom_payload("a", T0 + 0.05), T0 + 1.1)
    for k in range(3, 8):
        src.handle("a/odom", odom_payload("a", T0 + 0.1 * k), T0 + 1.1 + 0.01 * k)
        out += src.release(T0 + 1.1 + 0.01 * k)
    out += src.flush()
    assert len(out) == 7 and src.stats.out_of_order == late
    assert [a.event.t for a in out][:2] == (
        [T0 + 0.1, T0 + 0.05] if late else [T0 + 0.05, T0 + 0.1]
    )
