"""Heights from a robot's downward range finder (``height_topic``): the config's keys, a bag's
``sensor_msgs/msg/Range`` read into :class:`HeightEvent` (offset applied, readings outside the
message's limits dropped and counted), the message the replay writes read back the same on
both the fast and the full decoder, and simulated drones' heights reaching a live server's
``smoother3d`` localizer over Zenoh."""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from relloc.config import ConfigError, RobotConfig, TeamConfig
from relloc.events import HeightEvent
from relloc.ros.distros import layouts
from relloc.ros.messages import RANGE, decode, encode
from relloc.sensors import HEIGHT_SENSOR, Route
from relloc.sources.clock import HeaderClock
from relloc.sources.ingest import Converter, IngestStats, team_routes
from relloc.sources.rosbag import RosbagSource

ROBOTS = """
[[robots]]
name = "a"
uwb_node = "n_1"
[[robots]]
name = "b"
uwb_node = "n_2"
{extra}
"""


def _load(tmp_path: Path, extra: str) -> TeamConfig:
    path = tmp_path / "team.toml"
    path.write_text('reference = "a"\n' + ROBOTS.format(extra=extra))
    return TeamConfig.load(path)


def _team(offset: float = 0.0, sigma: float = 0.03) -> TeamConfig:
    robots = (
        RobotConfig(name="a", uwb_node="n_1"),
        RobotConfig(
            name="b",
            uwb_node="n_2",
            height_topic="/b/height",
            height_offset=offset,
            height_sigma=sigma,
        ),
    )
    return TeamConfig(robots=robots, reference="a", name="heights")


def _height_route(config: TeamConfig) -> Route:
    (route,) = [r for r in team_routes(config) if r.kind == HEIGHT_SENSOR.kind]
    return route


def _range(t: float, value: float, lo: float = 0.05, hi: float = 12.0) -> Any:
    """A range finder's ``sensor_msgs/msg/Range`` with its own limits."""
    msg = HEIGHT_SENSOR.message(HeightEvent(t, "b", value))
    return dataclasses.replace(msg, min_range=lo, max_range=hi)


# ---------------------------------------------------------------------------- config
def test_height_keys_round_trip_and_a_robot_without_writes_none(tmp_path: Path) -> None:
    config = _load(
        tmp_path, 'height_topic = "/b/height"\nheight_offset = -0.04\nheight_sigma = 0.02'
    )
    b = config.robot("b")
    assert (b.height_topic, b.height_offset, b.height_sigma) == ("/b/height", -0.04, 0.02)
    assert TeamConfig.from_dict(config.to_dict()) == config
    (tmp_path / "again.toml").write_text(config.to_toml())
    assert TeamConfig.load(tmp_path / "again.toml") == config
    a = config.to_dict()["robots"][0]
    assert not {"height_topic", "height_offset", "height_sigma"} & set(a)  # as before heights
    assert _team().robot("a").height_sigma == 0.03  # the default noise


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("height_sigma = 0.0", "height_sigma must be > 0"),
        ("height_sigma = -0.1", "height_sigma must be > 0"),
        ("height_sigma = nan", "height_sigma: expected a finite number"),
        ("height_offset = inf", "height_offset: expected a finite number"),
        ('height_offset = "low"', "height_offset: expected a finite number"),
        ("height_topic = 3", "height_topic: expected a string"),
    ],
)
def test_bad_height_keys_are_config_errors(tmp_path: Path, extra: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        _load(tmp_path, extra)


def test_only_robots_with_a_height_topic_have_a_height_route() -> None:
    route = _height_route(_team(offset=0.1, sigma=0.05))
    assert (route.topic, route.robot, route.msgtypes) == ("/b/height", "b", (RANGE,))


# ---------------------------------------------------------------------------- a bag
@pytest.mark.parametrize("distro", ["humble", "jazzy"])  # Range without and with its variance
def test_a_bag_of_range_finder_messages_becomes_heights(
    tmp_path: Path, bag_writer: Callable[..., Path], distro: str
) -> None:
    readings = [
        (10.0, 1.50, 0.05, 12.0),
        (10.1, 1.52, 0.05, 12.0),
        (10.2, 13.0, 0.05, 12.0),  # beyond max_range: nothing in range
        (10.3, 0.01, 0.05, 12.0),  # below min_range
        (10.4, math.nan, 0.05, 12.0),
        (10.5, 1.55, 0.0, 0.0),  # no limits given: any reading >= 0
        (10.6, 1.57, 0.05, 12.0),
    ]
    messages = [("/b/height", RANGE, t + 0.01, _range(t, v, lo, hi)) for t, v, lo, hi in readings]
    bag = bag_writer(tmp_path / "heights", messages, distro=distro)
    source = RosbagSource(bag, _team(offset=-0.12, sigma=0.02), ground_truth=False)
    events = list(source)
    assert all(isinstance(e, HeightEvent) for e in events)
    assert [(e.robot, e.t) for e in events] == [("b", t) for t in (10.0, 10.1, 10.5, 10.6)]
    assert [e.z for e in events] == pytest.approx([1.38, 1.40, 1.43, 1.45], abs=1e-6)
    assert {e.sigma for e in events} == {0.02}
    stats = source.stats
    assert stats.events["height"] == 4 and stats.messages["/b/height"] == 7
    assert stats.rejected == {"height_out_of_range": 2, "height_nonfinite": 1}
    assert "decode_error" not in stats.rejected


def test_a_missing_height_topic_lists_the_bag_topics(
    tmp_path: Path, bag_writer: Callable[..., Path]
) -> None:
    bag = bag_writer(tmp_path / "none", [("/a/height", RANGE, 1.0, _range(1.0, 1.0))])
    with pytest.raises(Exception, match=r"'/b/height' \(height of b\) is not in the bag"):
        RosbagSource(bag, _team(), ground_truth=False)


# ---------------------------------------------------------------------------- CDR
@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_the_message_written_is_read_back_by_both_decoders(distro: str) -> None:
    config = _team(offset=0.25, sigma=0.04)
    route = _height_route(config)
    event = HeightEvent(1_700_000_012.25, "b", 2.5, sigma=0.04)
    payload = encode(HEIGHT_SENSOR.message(event), distro=distro)
    layout = layouts(RANGE, distro)[0]
    fast = HEIGHT_SENSOR.fast(payload, layout)
    assert fast is not None and fast[1:] == pytest.approx((2.5, 0.0, 100.0))
    stats = IngestStats()
    got = Converter(stats, HeaderClock(), distro=distro).convert(route, route.topic, payload, 5.0)
    # the message is at the body origin: the reader adds the robot's own offset
    assert got == HeightEvent(event.t, "b", pytest.approx(2.75), 0.04)
    assert sum(stats.layouts.values()) == 1 and not stats.rejected
    # the full decoder's message (what a payload the fast path declines gets) reads the same
    assert HEIGHT_SENSOR.fast(payload + bytes(4), layout) is None
    msg = decode(payload, RANGE, layout)
    assert (
        HEIGHT_SENSOR.convert(route, route.topic, msg, None, got.t, Converter(stats, HeaderClock()))
        == got
    )


# ---------------------------------------------------------------------------- live
def test_simulated_drones_heights_reach_a_live_servers_localizer(
    sessions: tuple[Any, Any],
) -> None:
    pytest.importorskip("zenoh", reason="eclipse-zenoh is not installed: no live engine")
    from waiting import wait_until

    from relloc.live import LiveServer, ServeOptions
    from relloc.live.sim_robots import SimRobots, SimRobotsOptions, sim_team_config
    from relloc.simulator.flight import drones_scenario

    srv_session, client = sessions
    sim = drones_scenario(0, duration=4.0)
    config = sim_team_config(sim).with_filter(kind="smoother3d")
    assert {r.height_topic for r in config.robots} == {f"/d{i}/height" for i in range(5)}
    simulated = sum(isinstance(e, HeightEvent) for e in drones_scenario(0, duration=4.0).events())
    assert simulated > 100  # 10 Hz per drone
    rate = 2.0
    server = LiveServer(
        config, srv_session, ServeOptions(clock_rate=rate, reorder_window=1.0, status_period=0.5)
    )
    server.start()
    runner = threading.Thread(target=server.run, daemon=True)
    runner.start()
    robots = SimRobots(sim, config, client, SimRobotsOptions(rate=rate, wait=10.0))
    try:
        robots.run()
        ingested = server.source.stats.events
        assert wait_until(lambda: ingested["height"] >= simulated, 30.0)
    finally:
        server.stop()
        runner.join(timeout=30)
        robots.close()
        server.close()
    assert server.source.stats.rejected == {}
    assert server.pipelines[0].localizer.stats["height"] == simulated
