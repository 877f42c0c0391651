"""``relloc serve --foxglove``: a Foxglove WebSocket client (``tests/foxglove_client.py``) sees
the team as the app would, during a live serve of a simulated team and of the replayed shortbag.

serve, sim-robots and replay run as processes, Zenoh peers on 127.0.0.1 with multicast off; the
test's own Zenoh session hears serve's poses, and the client decodes every Foxglove channel. The
decoded poses must be the Zenoh ones (same estimate, same numbers); the shipped layout's topics
must be advertised whatever the robots' names. With ``--ground-truth`` on both sides the replayed
motion capture reaches the viewer (truth poses, errors) and changes no estimate. Every wait is on
a condition.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
from processes import relloc, write_sim_team
from waiting import wait_until

pytest.importorskip("foxglove")
pytest.importorskip("websockets")

from foxglove_client import FoxgloveClient

from relloc.config import TeamConfig
from relloc.live import ZenohOptions, free_tcp_port, open_session
from relloc.ros.messages import POSE_WITH_COVARIANCE_STAMPED, decode

REPO = Path(__file__).resolve().parents[1]
LAYOUT = REPO / "layouts" / "relloc.foxglove-layout.json"
SHORTBAG = "multi4_shortbag_20221011"


class ZenohPoses:
    """Every pose serve publishes on Zenoh: ``(robot, sec, nanosec) -> (x, y, frame_id)``."""

    def __init__(self, session: Any, robots: tuple[str, ...]) -> None:
        self._lock = threading.Lock()
        self.poses: dict[tuple[str, int, int], tuple[float, float, str]] = {}
        self.status: list[dict[str, Any]] = []
        self._subs = [
            session.declare_subscriber(
                f"relloc/{r}/pose", lambda s, r=r: self._on(r, s.payload.to_bytes())
            )
            for r in robots
        ]
        self._subs.append(
            session.declare_subscriber(
                "relloc/status", lambda s: self.status.append(json.loads(s.payload.to_bytes()))
            )
        )

    def _on(self, robot: str, data: bytes) -> None:
        msg = decode(data, POSE_WITH_COVARIANCE_STAMPED)
        p = msg.pose.pose.position
        key = (robot, int(msg.header.stamp.sec), int(msg.header.stamp.nanosec))
        with self._lock:
            self.poses[key] = (float(p.x), float(p.y), str(msg.header.frame_id))


def layout_topics(path: Path) -> set[str]:
    """Every topic a Foxglove layout's panels name (3D topics, plot paths, table topics)."""
    config = json.loads(path.read_text())["configById"]
    topics: set[str] = set()
    for panel in config.values():
        topics |= set(panel.get("topics", {}))
        for series in panel.get("paths", []):
            topics.add(series["value"].split(".", 1)[0])
        if "topicPath" in panel:
            topics.add(panel["topicPath"].split(".", 1)[0])
    return topics


def serve_with_viewer(
    tmp_path: Path,
    team: Path,
    feed: list[str],
    *,
    rate: float,
    foxglove_rate: float = 10.0,
    serve_args: tuple[str, ...] = (),
) -> tuple[FoxgloveClient, ZenohPoses, dict[str, Any]]:
    """Start serve with ``--foxglove`` (and ``serve_args``), connect a client and a Zenoh
    session, run ``feed`` (``relloc`` arguments of the source, connected to serve) to its end,
    stop serve."""
    config = TeamConfig.load(team)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    port = free_tcp_port()
    summary = tmp_path / "serve.json"
    serve = relloc(
        "serve", "--config", str(team), "--clock-rate", str(rate), "--json", str(summary),
        "--foxglove", f"127.0.0.1:{port}", "--foxglove-rate", str(foxglove_rate),
        "--listen", endpoint, "--no-multicast", *serve_args, log=tmp_path / "serve.log",
    )  # fmt: skip
    procs = [serve]
    session = open_session(ZenohOptions(connect=(endpoint,), multicast=False))
    client = None
    try:
        zenoh = ZenohPoses(session, config.others)
        log = (tmp_path / "serve.log").read_text
        assert wait_until(lambda: bool(zenoh.status), timeout=60.0), log()
        client = FoxgloveClient("127.0.0.1", port)
        expected = {f"/relloc/{r}/pose" for r in config.others} | {
            "/relloc/poses",
            "/relloc/truth_poses",
            "/relloc/scene",
            "/relloc/flags",
            "/relloc/status",
        }
        assert wait_until(lambda: expected <= client.topics(), timeout=30.0), (
            client.topics(),
            client.error,
        )
        # subscribed once the status arrives through Foxglove: serve has the subscription
        assert wait_until(lambda: bool(client.received("/relloc/status")), timeout=30.0)
        src = relloc(*feed, "--no-multicast", "--connect", endpoint, log=tmp_path / "feed.log")
        procs.append(src)
        assert src.wait(timeout=180) == 0, (tmp_path / "feed.log").read_text()
        # serve has every message once its received count stops moving for a status period
        seen: list[int] = []

        def settled() -> bool:
            seen.append(zenoh.status[-1]["source"]["messages"])
            return len(seen) > 150 and seen[-1] == seen[-150] > 0

        assert wait_until(settled, timeout=60.0)
        serve.send_signal(signal.SIGTERM)
        assert serve.wait(timeout=60) == 0, log()
    finally:
        if client is not None:
            client.close()
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        session.close()
    assert client.error is None, client.error
    return client, zenoh, json.loads(summary.read_text())


def check_channels(client: FoxgloveClient, zenoh: ZenohPoses, robots: tuple[str, ...]) -> None:
    """Every channel decodes; every Foxglove pose is the Zenoh pose of its stamp."""
    for robot in robots:
        got = client.received(f"/relloc/{robot}/pose")
        assert got, robot
        for i, (_, msg) in enumerate(got):
            key = (robot, msg.timestamp.seconds, msg.timestamp.nanos)
            if key not in zenoh.poses and i == len(got) - 1:
                continue  # the last, fused as serve stopped, may not have reached the session
            x, y, frame = zenoh.poses[key]
            assert (msg.pose.position.x, msg.pose.position.y) == (x, y)
            assert msg.frame_id == frame
    many = client.received("/relloc/poses")
    assert many and all(len(m.poses) <= len(robots) for _, m in many)
    assert any(len(m.poses) == len(robots) for _, m in many)
    scenes = client.received("/relloc/scene")
    assert scenes
    ids = {e.id for _, s in scenes for e in s.entities}
    assert {f"robot/{r}" for r in robots} <= ids
    assert any(i.startswith("range/") for i in ids)
    flags = client.received("/relloc/flags")
    assert flags and set(flags[-1][1]["robots"]) == set(robots)
    assert [e["robot"] for e in flags[-1][1]["by_index"]] == list(robots)
    assert {"orientation_observable", "inconsistent", "recovering", "unseen"} <= set(flags[-1][1])
    assert client.received("/relloc/status")[-1][1]["team"]


def rate_of(got: list[tuple[float, Any]]) -> float:
    """Messages a second between the first and the last received."""
    return (len(got) - 1) / max(got[-1][0] - got[0][0], 1e-9)


@pytest.mark.slow
def test_a_client_sees_the_simulated_team_in_foxglove(tmp_path: Path) -> None:
    team = tmp_path / "team.toml"
    write_sim_team(team)
    feed = ["sim-robots", "--scenario", "multi", "--config", str(team), "--rate", "2",
            "--duration", "15", "--no-ground-truth"]  # fmt: skip
    client, zenoh, summary = serve_with_viewer(tmp_path, team, feed, rate=2.0)
    robots = TeamConfig.load(team).others
    check_channels(client, zenoh, robots)
    assert not any(r.startswith("turtle") for r in robots)  # the layout serves this team too
    assert layout_topics(LAYOUT) <= client.topics(), layout_topics(LAYOUT) - client.topics()
    assert not client.received("/relloc/truth_poses")  # no motion capture asked for
    rates = {r: rate_of(client.received(f"/relloc/{r}/pose")) for r in robots}
    print(f"\nsim: pose messages/s {rates}, estimates {summary['methods']['pf']['estimates']}")
    assert all(rate <= 10.0 * 1.2 for rate in rates.values())  # --foxglove-rate 10


@pytest.mark.slow
@pytest.mark.shared_data
def test_the_replayed_shortbag_in_foxglove(tmp_path: Path, shared_data: Path) -> None:
    """The acceptance run: the shortbag at 2x with its motion capture, at least 5 poses a
    second per robot, its truth and errors in the viewer."""
    team = REPO / "configs" / "tiers" / f"{SHORTBAG}.toml"
    feed = ["replay", str(shared_data / "tiers" / SHORTBAG), "--config", str(team), "--rate", "2",
            "--ground-truth"]  # fmt: skip
    client, zenoh, summary = serve_with_viewer(
        tmp_path, team, feed, rate=2.0, serve_args=("--ground-truth",)
    )
    robots = TeamConfig.load(team).others
    check_channels(client, zenoh, robots)
    assert layout_topics(LAYOUT) <= client.topics()  # the layout is this team's too
    truths = {r: len(client.received(f"/relloc/{r}/truth")) for r in robots}
    truth_poses = client.received("/relloc/truth_poses")
    assert all(n > 0 for n in truths.values()), truths
    assert truth_poses and any(len(m.poses) == len(robots) for _, m in truth_poses)
    flags = [f for _, f in client.received("/relloc/flags")]
    errors = {
        r: [f["robots"][r]["error_m"] for f in flags if "error_m" in f["robots"][r]] for r in robots
    }
    assert all(errors.values()), errors
    by_index = [f["by_index"][i].get("error_m") for f in flags for i in range(len(robots))]
    assert sorted(e for e in by_index if e is not None) == sorted(
        e for v in errors.values() for e in v
    )
    medians = {r: round(sorted(e)[len(e) // 2], 3) for r, e in errors.items()}
    print(f"\nshortbag 2x truth: messages {truths}, truth_poses {len(truth_poses)}, "
          f"error_m median {medians} over {[len(e) for e in errors.values()]} flags")  # fmt: skip
    assert all(m < 2.0 for m in medians.values()), medians
    rates = {r: rate_of(client.received(f"/relloc/{r}/pose")) for r in robots}
    n = {r: len(client.received(f"/relloc/{r}/pose")) for r in robots}
    print(f"\nshortbag 2x: pose messages/s {rates}, messages {n}, "
          f"estimates {summary['methods']['pf']['estimates']}")  # fmt: skip
    assert all(rate >= 5.0 for rate in rates.values()), rates


def test_the_layout_names_only_advertised_topics(tmp_path: Path) -> None:
    """The shipped layout opens on what a server advertises (no live data needed)."""
    from relloc.sinks.foxglove import FoxgloveSink

    config = TeamConfig.load(REPO / "configs" / "tiers" / f"{SHORTBAG}.toml")
    sink = FoxgloveSink(config, "127.0.0.1:0")
    client = FoxgloveClient("127.0.0.1", sink.port, wanted=lambda topic: False)
    try:
        assert wait_until(lambda: len(client.topics()) == len(sink.topics), timeout=30.0)
        topics = layout_topics(LAYOUT)
        assert topics and topics <= client.topics(), topics - client.topics()
        assert any(t.endswith("/scene") for t in topics)
        assert "/relloc/flags" in topics
    finally:
        client.close()
        sink.close()
    assert client.error is None


def test_without_the_extra_foxglove_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    from relloc.cli.common import UserError
    from relloc.cli.live import _check_foxglove

    with pytest.raises(UserError, match="HOST"):
        _check_foxglove("localhost:port")
    monkeypatch.setitem(sys.modules, "foxglove", None)
    with pytest.raises(UserError, match=r"relloc\[viewer\]"):
        _check_foxglove("8765")


def test_ground_truth_without_a_viewer_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    """Only the viewer uses motion capture: ``--ground-truth`` alone would receive it for nothing."""
    from relloc.cli import main

    team = REPO / "configs" / "tiers" / f"{SHORTBAG}.toml"
    assert main(["serve", "--config", str(team), "--ground-truth", "--no-multicast"]) == 2
    assert "--foxglove" in capsys.readouterr().err


def test_with_motion_capture_every_truth_channel_is_advertised_from_the_start() -> None:
    """A client that connects before the first motion capture subscribes to the truth with
    the rest (a channel made later could be missed by a client connecting meanwhile)."""
    from relloc.live import LiveServer, ServeOptions

    config = TeamConfig.load(REPO / "configs" / "tiers" / f"{SHORTBAG}.toml")
    session = open_session(ZenohOptions(multicast=False))
    server = LiveServer(
        config, session, ServeOptions(foxglove="127.0.0.1:0", ground_truth=True, particles=100)
    )
    assert server.viewer is not None
    client = FoxgloveClient("127.0.0.1", server.viewer.port, wanted=lambda topic: False)
    try:
        truths = {f"/relloc/{r}/truth" for r in config.others}
        assert wait_until(lambda: truths <= client.topics(), timeout=30.0), client.topics()
    finally:
        client.close()
        server.close()
        session.close()
    assert client.error is None


def test_an_onboard_serve_advertises_its_teammates_below_its_name() -> None:
    from relloc.live import LiveServer, ServeOptions

    config = TeamConfig.load(REPO / "configs" / "tiers" / f"{SHORTBAG}.toml")
    session = open_session(ZenohOptions(multicast=False))
    server = LiveServer(
        config, session, ServeOptions(robot="turtle01", foxglove="127.0.0.1:0", particles=100)
    )
    assert server.viewer is not None
    client = FoxgloveClient("127.0.0.1", server.viewer.port, wanted=lambda topic: False)
    try:
        expected = {f"/relloc/turtle01/{r}/pose" for r in ("turtle03", "turtle04", "turtle05")}
        expected |= {
            f"/relloc/turtle01/{c}" for c in ("poses", "truth_poses", "scene", "flags", "status")
        }
        assert wait_until(lambda: client.topics() == expected, timeout=30.0), client.topics()
    finally:
        client.close()
        server.close()
        session.close()
    assert client.error is None


@pytest.mark.slow
@pytest.mark.shared_data
def test_the_truth_subscription_changes_no_estimate(shared_data: Path) -> None:
    """The shortbag's messages, motion capture included, through the live source's own path
    (:meth:`ZenohSource.handle`, no network: deterministic) into a server with and without
    ``ground_truth``: the viewer gets every motion-capture pose, the estimates are identical."""
    from rosbags.rosbag2 import Reader

    from relloc.events import GroundTruthEvent
    from relloc.live import LiveServer, ServeOptions

    config = TeamConfig.load(REPO / "configs" / "tiers" / f"{SHORTBAG}.toml")
    session = open_session(ZenohOptions(multicast=False))
    runs: dict[bool, tuple[list[Any], list[GroundTruthEvent]]] = {}
    try:
        for truth in (False, True):
            server = LiveServer(
                config,
                session,
                ServeOptions(particles=300, seed=0, foxglove="127.0.0.1:0", ground_truth=truth),
            )
            assert server.viewer is not None
            seen: list[GroundTruthEvent] = []
            server.engine.truth_sinks.append(seen.append)
            try:
                with Reader(shared_data / "tiers" / SHORTBAG) as reader:
                    for conn, ns, raw in reader.messages():
                        key = server.options.interface.topic_key(conn.topic)
                        if key in server.source.routes:
                            server.source.handle(key, bytes(raw), ns * 1e-9)
                            server.feed(server.source.release(ns * 1e-9))
                server.feed(server.source.flush())
                server.engine.finish()
            finally:
                server.close()
            assert server.source.stats.rejected == {}
            estimates = [
                (e.t, {r: tuple(p) for r, p in e.positions.items()})
                for e in server.pipelines[0].estimates
            ]
            runs[truth] = (estimates, seen)
    finally:
        session.close()
    assert runs[False][1] == []
    truths = runs[True][1]
    assert {e.robot for e in truths} == set(config.robot_names)
    assert runs[True][0] == runs[False][0] and len(runs[False][0]) > 50
    print(f"\n{len(truths)} motion-capture poses; {len(runs[True][0])} estimates, identical")
