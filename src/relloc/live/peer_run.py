"""A whole run of the independent ROS 2 peer against ``relloc serve``.

:class:`TeamTopics` reads a relloc team config, :class:`TeamPublisher` publishes a simulated
team's odometry and ranges through the SDK's publishers (:mod:`relloc.live.ros2_peer`),
:class:`PoseInbox` collects what ``relloc serve`` publishes, :func:`ape_medians` scores it
against the simulator's truth, :class:`RellocProcess` runs ``relloc serve`` or ``sim-robots``
itself and :func:`run_against_serve` is the whole run (``scripts/ros2_peer_check.py``).
"""

from __future__ import annotations

import json
import math
import signal
import socket
import subprocess
import sys
import tempfile
import time
import tomllib
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from relloc.live.ros2_peer import (
    HASH_NOT_SUPPORTED,
    ODOMETRY,
    POSE,
    RANGE,
    STRING,
    TIME_BASE,
    TWIST,
    Ros2Peer,
    write_messages,
)


# ---------------------------------------------------------------------------- the team
@dataclass(frozen=True)
class TeamTopics:
    """The ROS topics of a relloc team config (TOML): odometry per robot, ranges per node pair."""

    reference: str
    robots: tuple[str, ...]
    odom: dict[str, str]
    """Robot -> fully qualified odometry topic (below its ``zenoh_scope``)."""
    nodes: dict[str, str]
    """UWB node -> robot."""
    scopes: dict[str, str]
    range_template: str

    @classmethod
    def load(cls, path: Path) -> TeamTopics:
        data = tomllib.loads(Path(path).read_text())
        robots = data["robots"]
        scopes = {r["name"]: r.get("zenoh_scope", "") for r in robots}
        odom = {
            r["name"]: _qualified(r.get("odom_topic") or f"/{r['name']}/odom", scopes[r["name"]])
            for r in robots
        }
        return cls(
            reference=data["reference"],
            robots=tuple(r["name"] for r in robots),
            odom=odom,
            nodes={
                node: r["name"]
                for r in robots
                for node in ([r["uwb_node"]] if r.get("uwb_node") else [])
                + [t["node"] for t in r.get("tags", [])]
            },
            scopes=scopes,
            range_template=data.get("uwb", {}).get("range_topic", "/uwb/tof/{a}/{b}/distance"),
        )

    @property
    def others(self) -> tuple[str, ...]:
        return tuple(r for r in self.robots if r != self.reference)

    def range_topic(self, node_a: str, node_b: str) -> str:
        """The topic of ranges from ``node_a`` to ``node_b`` (below ``node_a``'s robot's scope)."""
        topic = self.range_template.format(a=node_a, b=node_b)
        return _qualified(topic, self.scopes[self.nodes[node_a]])

    def range_topics(self) -> list[str]:
        """Every ordered pair's range topic."""
        nodes = sorted(self.nodes)
        return [self.range_topic(a, b) for a in nodes for b in nodes if a != b]

    def pose_topic(self, robot: str, prefix: str = "relloc") -> str:
        """Where ``relloc serve`` publishes ``robot``'s pose."""
        return f"/{prefix.strip('/')}/{robot}/pose"


def _qualified(topic: str, scope: str) -> str:
    parts = [p.strip("/") for p in (scope, topic)]
    return "/" + "/".join(p for p in parts if p)


def _stamp(t: float, types: Any) -> Any:
    sec = math.floor(t)
    return types["builtin_interfaces/msg/Time"](
        sec=int(sec), nanosec=round((t - sec) * 1e9) % 10**9
    )


class TeamPublisher:
    """A simulated team's odometry (``nav_msgs/Odometry`` per robot) and ranges
    (``sensor_msgs/Range`` per ordered node pair) through the peer's SDK publishers."""

    def __init__(self, peer: Ros2Peer, topics: TeamTopics, events: Sequence[Any]) -> None:
        from relloc.events import OdometryEvent, RangeEvent

        self.peer = peer
        self.topics = topics
        self.items: list[tuple[float, str, Any]] = []
        """``(t, topic, event)`` in time order."""
        for ev in events:
            if isinstance(ev, OdometryEvent) and ev.robot in topics.odom:
                self.items.append((ev.t, topics.odom[ev.robot], ev))
            elif (
                isinstance(ev, RangeEvent)
                and ev.node_a in topics.nodes
                and ev.node_b in topics.nodes
            ):
                self.items.append((ev.t, topics.range_topic(ev.node_a, ev.node_b), ev))
        self.items.sort(key=lambda item: item[0])
        self.pubs: dict[str, Any] = {}
        for _, topic, ev in self.items:
            if topic not in self.pubs:
                msgtype = ODOMETRY if isinstance(ev, OdometryEvent) else RANGE
                node = f"{ev.robot}_base" if msgtype == ODOMETRY else "uwb_driver"
                self.pubs[topic] = peer.publisher(topic, msgtype, node=node)
        self.sent: Counter[str] = Counter()
        self.max_behind = 0.0

    def matched(self) -> bool:
        """Whether every publisher has a subscriber (relloc serve's)."""
        return all(p.pub.matching_status.matching for p in self.pubs.values())

    def run(
        self, rate: float, time_base: float = TIME_BASE, stop: Callable[[], bool] = lambda: False
    ) -> int:
        """Publish every item at ``rate`` times its pace; returns the number published."""
        from relloc.events import OdometryEvent

        types = self.peer.types()
        start = time.time()
        first = self.items[0][0] if self.items else 0.0
        for t, topic, ev in self.items:
            if stop():
                break
            delay = start + (t - first) / rate - time.time()
            if delay > 0:
                time.sleep(delay)
            else:
                self.max_behind = max(self.max_behind, -delay)
            stamp = _stamp(t + time_base, types)
            if isinstance(ev, OdometryEvent):
                header = types["std_msgs/msg/Header"](stamp=stamp, frame_id="odom")
                self.pubs[topic].publish(**self._odometry(ev, header, types))
            else:
                header = types["std_msgs/msg/Header"](stamp=stamp, frame_id="")
                self.pubs[topic].publish(**self._range(ev, header))
            self.sent[topic] += 1
        return sum(self.sent.values())

    @staticmethod
    def _odometry(ev: Any, header: Any, types: Any) -> dict[str, Any]:
        vec, zero36 = types["geometry_msgs/msg/Vector3"], np.zeros(36, dtype=np.float64)
        pose = types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=float(ev.x), y=float(ev.y), z=0.0),
            orientation=types["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(ev.yaw / 2), w=math.cos(ev.yaw / 2)
            ),
        )
        twist = types[TWIST](
            linear=vec(x=float(ev.v), y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=float(ev.w))
        )
        return {
            "header": header,
            "child_frame_id": "base_link",
            "pose": types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=zero36),
            "twist": types["geometry_msgs/msg/TwistWithCovariance"](
                twist=twist, covariance=zero36.copy()
            ),
        }

    def _range(self, ev: Any, header: Any) -> dict[str, Any]:
        fields = {
            "header": header, "radiation_type": 0, "field_of_view": 0.0, "min_range": 0.0,
            "max_range": 0.0, "range": float(ev.distance),
        }  # fmt: skip
        if self.peer.distro != "humble":
            fields["variance"] = 0.0
        return fields


# ---------------------------------------------------------------------------- what serve says
class PoseInbox:
    """SDK subscribers of every robot's pose (``geometry_msgs/PoseWithCovarianceStamped``) and
    of serve's status (``std_msgs/String`` JSON) below ``prefix``, from a serve of
    ``serve_distro`` (its hashes; default: the peer's distribution)."""

    def __init__(
        self, peer: Ros2Peer, topics: TeamTopics, *, serve_distro: str | None = None,
        prefix: str = "relloc",
    ) -> None:  # fmt: skip
        self.topics = topics
        serve_distro = serve_distro or peer.distro

        def hash_of(msgtype: str) -> str:
            return HASH_NOT_SUPPORTED if serve_distro == "humble" else peer.rihs01(msgtype)

        self.poses = {
            r: peer.subscribe(topics.pose_topic(r, prefix), POSE, type_hash=hash_of(POSE))
            for r in topics.others
        }
        self.status = peer.subscribe(
            f"/{prefix.strip('/')}/status", STRING, type_hash=hash_of(STRING)
        )

    def counts(self) -> dict[str, int]:
        return {r: inbox.count for r, inbox in self.poses.items()}

    def last_status(self) -> dict[str, Any] | None:
        msgs = self.status.snapshot()
        return json.loads(msgs[-1].data) if msgs else None

    def estimates(self) -> list[Any]:
        """The poses as relloc estimates, one per stamp, in time order (frame: the reference)."""
        from relloc.estimate import Estimate, Position

        grouped: dict[float, dict[str, Position]] = {}
        for robot, inbox in self.poses.items():
            for msg in inbox.snapshot():
                t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
                p = msg.pose.pose.position
                grouped.setdefault(t, {})[robot] = (float(p.x), float(p.y))
        return [
            Estimate(t=t, method="pf", reference=self.topics.reference, positions=pos)
            for t, pos in sorted(grouped.items())
        ]

    def frames(self) -> set[str]:
        return {m.header.frame_id for inbox in self.poses.values() for m in inbox.snapshot()}


def ape_medians(
    estimates: Sequence[Any], truth: Iterable[Any], reference: str, robots: Iterable[str],
    *, start: float, time_base: float = TIME_BASE,
) -> dict[str, tuple[float, int]]:  # fmt: skip
    """Per robot ``(APE median m, n)`` of ``estimates`` from ``start`` (s of simulated time) on,
    against the simulator's ground-truth events: relloc's own scoring (positions relative to
    the reference's, world axes; :func:`relloc.evaluation.metrics.associate`)."""
    from dataclasses import replace

    from relloc.evaluation.metrics import ApeStats, GroundTruth, after, associate
    from relloc.events import GroundTruthEvent

    gt = GroundTruth(reference)
    for ev in truth:
        if isinstance(ev, GroundTruthEvent):
            gt.add(replace(ev, t=ev.t + time_base))
    out: dict[str, tuple[float, int]] = {}
    for robot, paired in associate(estimates, gt, robots).items():
        stats = ApeStats.of(after(paired, time_base + start).errors)
        out[robot] = (stats.median, stats.n)
    return out


def clean_team(seed: int = 0, robots: int = 4, duration: float = 20.0) -> Any:
    """A simulated team with near-perfect sensors: the grid scenario, unbiased UWB with 2 cm of
    white noise and no outliers or losses, odometry without errors."""
    from relloc.simulator.error_models import OdometryErrorModel, UwbErrorModel
    from relloc.simulator.scenarios import grid_scenario

    uwb = UwbErrorModel(
        bias_range=(0.0, 0.0), orientation_amplitude=0.0, sigma=0.02, nlos_probability=0.0,
        dropout_probability=0.0,
    )  # fmt: skip
    odometry = OdometryErrorModel(
        scale_range=(1.0, 1.0), sigma_v=0.0, sigma_w=0.0, gyro_bias_max=0.0
    )
    return grid_scenario(seed, robots=robots, duration=duration, uwb=uwb, odometry=odometry)


def save_team_config(sim: Any, path: Path) -> Path:
    """The simulator's config (truthful calibration) with odometry on ``/<robot>/odom``, saved."""
    config = sim.config
    for robot in config.robot_names:
        config = config.with_robot(robot, odom_topic=f"/{robot}/odom")
    config.save(path)
    return path


# ---------------------------------------------------------------------------- relloc processes
def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(condition: Callable[[], bool], timeout: float = 10.0, period: float = 0.02) -> bool:
    """Poll ``condition`` until it holds or ``timeout`` s have passed; its last value."""
    end = time.time() + timeout
    while time.time() < end:
        if condition():
            return True
        time.sleep(period)
    return bool(condition())


def _listening(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.2):
            return True
    except OSError:
        return False


class RellocProcess:
    """A ``relloc`` command listening on ``tcp/127.0.0.1:port`` (multicast off); stopped with
    SIGTERM. Its output goes to a file (a pipe could fill and block it), read into
    :attr:`output` when it has stopped."""

    def __init__(self, args: Sequence[str], port: int, *, startup: float = 30.0) -> None:
        self.port = port
        self.args = [
            sys.executable, "-m", "relloc.cli", *args,
            "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast",
        ]  # fmt: skip
        self._log = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 (closed by stop)
        self.proc = subprocess.Popen(
            self.args, stdout=self._log, stderr=subprocess.STDOUT, text=True
        )
        self.output = ""
        if not wait_for(lambda: _listening(port) or self.proc.poll() is not None, startup, 0.05):
            self.stop()
            raise RuntimeError(f"{' '.join(self.args)} never listened: {self.output}")
        if self.proc.poll() is not None:
            self.stop()
            raise RuntimeError(f"{' '.join(self.args)} exited: {self.output}")

    def stop(self, timeout: float = 30.0) -> int:
        """SIGTERM (unless it has ended), wait, return the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if not self._log.closed:
            self._log.seek(0)
            self.output = self._log.read()
            self._log.close()
        return int(self.proc.returncode)

    def __enter__(self) -> RellocProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def serve_args(
    config: Path, distro: str | None, summary: Path, *, particles: int = 1000, rate: float = 1.0,
    reorder_window: float = 0.0,
) -> list[str]:  # fmt: skip
    """``relloc serve`` on rmw_zenoh for robots of ``distro`` (``None``: its default), its
    clock at ``rate``, status four times a second, final figures to ``summary``."""
    args = [
        "serve", "--config", str(config), "--ros-interface", "rmw_zenoh",
        "--particles", str(particles), "--clock-rate", f"{rate:g}", "--status-period", "0.25",
        "--reorder-window", f"{reorder_window:g}", "--json", str(summary),
    ]  # fmt: skip
    return [*args, "--ros-distro", distro] if distro else args


@dataclass(frozen=True)
class PeerRun:
    """How a team run against serve goes (:func:`run_against_serve`)."""

    distro: str = "jazzy"
    """The peer's definitions."""
    serve_distro: str | None = None
    """serve's ``--ros-distro`` (default: the peer's)."""
    seed: int = 0
    robots: int = 4
    duration: float = 30.0
    """Simulated seconds."""
    rate: float = 6.0
    """Simulated seconds per wall second (serve's ``--clock-rate`` too)."""
    particles: int = 2000
    reorder_window: float = 0.4
    """serve's, so that arrivals interleaved by Zenoh's threads reach the filter in stamp
    order: the same estimates every run."""
    warmup: float = 10.0
    """Simulated seconds left out of the APE."""


def run_against_serve(run: PeerRun, work: Path) -> dict[str, Any]:
    """A clean simulated team (:func:`clean_team`) published by the SDK with ``run.distro``'s
    definitions to ``relloc serve --ros-interface rmw_zenoh`` (its own process, on loopback);
    the SDK collects serve's poses and status and lists the ROS graph before serve stops.

    Returns the figures: messages sent, serve's estimates, poses received per robot, APE
    medians, serve's rejection and transport counters (its ``--json`` summary), the topics and
    endpoints the SDK discovered, and the git clones the SDK attempted (none, or it is broken).
    """
    sim = clean_team(run.seed, run.robots, run.duration)
    events = list(sim.events())
    config = save_team_config(sim, work / "team.toml")
    topics = TeamTopics.load(config)
    messages = write_messages(run.distro, work / f"msg_{run.distro}")
    summary_path = work / "summary.json"
    serve_distro = run.serve_distro or run.distro
    port = free_port()
    t0 = time.time()
    args = serve_args(
        config, serve_distro, summary_path, particles=run.particles, rate=run.rate,
        reorder_window=run.reorder_window,
    )  # fmt: skip
    with RellocProcess(args, port) as serve, Ros2Peer(run.distro, messages, port) as peer:
        inbox = PoseInbox(peer, topics, serve_distro=serve_distro)
        team = TeamPublisher(peer, topics, events)
        if not wait_for(team.matched, 30.0):
            raise RuntimeError("relloc serve never subscribed to every topic")
        sent = team.run(run.rate)

        def received() -> bool:
            status = inbox.last_status()
            return status is not None and status["source"]["messages"] >= sent

        all_in = wait_for(received, 30.0)
        graph = peer.topics(timeout=1.0)
        watched = [*(topics.pose_topic(r) for r in topics.others), "/relloc/status"]
        ranges = sorted(set(team.pubs) - set(topics.odom.values()))
        watched += [topics.odom[topics.robots[-1]], *ranges[:1]]
        endpoints = {}
        for topic in dict.fromkeys(watched):
            info = peer.topic_info(topic, timeout=1.0)
            endpoints[topic] = None if info is None else {
                "types": list(info.topic_types),
                "publishers": sorted({(e.node_name, e.type_hash) for e in info.publishers}),
                "subscribers": sorted({(e.node_name, e.type_hash) for e in info.subscribers}),
            }  # fmt: skip
        code = serve.stop()
        summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        published = summary.get("methods", {}).get("pf", {}).get("estimates", 0)
        wait_for(lambda: min(inbox.counts().values()) >= published, 10.0)
        apes = ape_medians(
            inbox.estimates(), events, topics.reference, topics.others, start=run.warmup
        )
        return {
            "distro": run.distro,
            "serve_distro": serve_distro,
            "robots": list(topics.robots),
            "reference": topics.reference,
            "simulated_s": run.duration,
            "rate": run.rate,
            "wall_s": round(time.time() - t0, 1),
            "sent": sent,
            "publishers": len(team.pubs),
            "max_behind_s": round(team.max_behind, 4),
            "serve_received_all": all_in,
            "serve_exit": code,
            "serve_output": serve.output,
            "serve_estimates": published,
            "poses_received": inbox.counts(),
            "pose_frames": sorted(inbox.frames()),
            "status_messages": inbox.status.count,
            "ape_median_m": {r: m for r, (m, _) in apes.items()},
            "ape_n": {r: n for r, (_, n) in apes.items()},
            "rejected": summary.get("source", {}).get("rejected"),
            "transport": summary.get("source", {}).get("transport"),
            "topics": graph,
            "endpoints": endpoints,
            "clone_attempts": list(peer.clone_attempts),
        }
