"""The live navigation system over Zenoh on loopback: ``relloc sim-robots`` + ``relloc serve`` +
``relloc navigate`` as separate processes, and Ctrl-C of ``relloc navigate``.

Every session is a peer on 127.0.0.1 with explicit listen/connect endpoints on free ports and
multicast scouting off: no other service, nothing leaves the machine. The simulated team runs
twice as fast as real time (``--rate 2``) and the server and the navigator are told so
(``--clock-rate 2``): every clock, the control period included, runs twice as fast, so the
system is the real one, sped up. The server fuses the events in stamp order (``--reorder-window
0.1``) and sim-robots starts its clock on a whole second, so a run's estimates do not depend on
the order the messages happened to arrive in (docs/howto/navigation.md, "Run-to-run spread").
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from processes import relloc

from relloc.live import ZenohOptions, free_tcp_port, open_session
from relloc.navigation.path import load_path
from relloc.ros.messages import (
    TWIST,
    decode,
    encode,
    odometry_msg,
    pose_with_covariance_msg,
)

REPO = Path(__file__).resolve().parents[1]
SMALL = REPO / "configs" / "paths" / "small_rectangle.toml"


def stop(proc: subprocess.Popen[bytes], timeout: float = 15.0) -> int:
    """SIGINT, then wait (kill if it hangs)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


def zenoh_args(*, listen: int | None = None, connect: int | None = None) -> list[str]:
    args = ["--no-multicast"]
    if listen is not None:
        args += ["--listen", f"tcp/127.0.0.1:{listen}"]
    if connect is not None:
        args += ["--connect", f"tcp/127.0.0.1:{connect}"]
    return args


def write_team(tmp: Path, particles: int = 4000) -> Path:
    """The simulated nav team's config, written by ``relloc sim-robots --config-only``."""
    team = tmp / "team.toml"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "relloc.cli",
            "sim-robots",
            "--scenario",
            "nav",
            "--config-only",
            "--write-config",
            str(team),
            "--particles",
            str(particles),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    return team


def start_sim_robots(tmp: Path, team: Path, port: int, *extra: str) -> subprocess.Popen[bytes]:
    """``relloc sim-robots`` for the nav scenario at twice real time, listening on ``port``,
    writing its truth to ``tmp/sim.json``."""
    return relloc(
        "sim-robots",
        "--scenario",
        "nav",
        "--config",
        str(team),
        "--rate",
        "2",
        "--duration",
        "120",
        "--json",
        str(tmp / "sim.json"),
        *extra,
        *zenoh_args(listen=port),
        log=tmp / "sim.log",
    )


def start_navigate(tmp: Path, team: Path, port: int, *extra: str) -> subprocess.Popen[bytes]:
    """``relloc navigate`` of r2 along the small rectangle for 50 s at twice real time,
    connecting to ``port``, writing its summary to ``tmp/nav.json``."""
    return relloc(
        "navigate",
        "--config",
        str(team),
        "--robot",
        "r2",
        "--path",
        str(SMALL),
        *extra,
        "--clock-rate",
        "2",
        "--duration",
        "50",
        "--json",
        str(tmp / "nav.json"),
        *zenoh_args(connect=port),
        log=tmp / "nav.log",
    )


def drive_small_rectangle(tmp: Path, *interface: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """sim-robots + serve + navigate (each given ``interface``, e.g. the rmw_zenoh flags) on
    loopback until navigate ends; returns navigate's summary and sim-robots' (with the truth)."""
    team = write_team(tmp)
    port = free_tcp_port()
    procs = []
    try:
        procs.append(start_sim_robots(tmp, team, port, *interface))
        serve = relloc(
            "serve",
            "--config",
            str(team),
            "--clock-rate",
            "2",
            "--reorder-window",
            "0.1",
            *interface,
            *zenoh_args(connect=port),
            log=tmp / "serve.log",
        )
        procs.append(serve)
        nav = start_navigate(tmp, team, port, *interface)
        procs.append(nav)
        try:
            code = nav.wait(timeout=75)
        except subprocess.TimeoutExpired:
            code = None
        logs = {p.name: p.read_text() for p in tmp.glob("*.log")}
        assert code == 0, f"navigate ended with {code}:\n" + "\n".join(
            f"--- {k}\n{v}" for k, v in logs.items()
        )
    finally:
        for proc in reversed(procs):
            stop(proc)
    return json.loads((tmp / "nav.json").read_text()), json.loads((tmp / "sim.json").read_text())


def check_small_rectangle(summary: dict[str, Any], truth: dict[str, Any]) -> None:
    """The path was completed, with the robot (the simulator's truth) close to it."""
    assert summary["completed"] is True and summary["ended"] == "goal reached"
    assert [s["reason"] for s in summary["stops"]][-2:] == ["released", "goal reached"]
    assert truth["commands_received"] > 50
    # Tracking error: the robot's true position (the simulator's) against the planned path, from
    # reaching the first waypoint to completing the path.
    r2 = np.array(truth["truth"]["r2"])
    r0 = np.array(truth["truth"]["r0"])
    rel = r2[:, 1:3] - r0[:, 1:3]
    window = (r2[:, 0] >= summary["path_start_t"]) & (r2[:, 0] <= summary["end_t"])
    errors = load_path(SMALL).distance(rel[window])
    assert errors.size > 100
    print(f"live tracking error: median {np.median(errors):.3f} m, std {errors.std():.3f} m")
    assert float(np.median(errors)) < 0.2
    # And the robot stopped at the end.
    last = r2[r2[:, 0] > summary["end_t"] + 1.0]
    if len(last) > 1:
        assert np.ptp(last[:, 1]) < 1e-6 and np.ptp(last[:, 2]) < 1e-6


@pytest.mark.slow
def test_sim_robots_serve_and_navigate_drive_a_small_rectangle_over_zenoh(tmp_path: Path) -> None:
    summary, truth = drive_small_rectangle(tmp_path)
    assert summary["cmd_vel_key"] == "r2/cmd_vel" and summary["estimate_key"] == "relloc/r2/pose"
    check_small_rectangle(summary, truth)


@pytest.mark.slow
def test_the_same_loop_on_rmw_zenoh(tmp_path: Path) -> None:
    """The three processes as rmw_zenoh nodes on ROS domain 7: rmw_zenoh keys (type names and
    RIHS01 hashes), attachments and liveliness tokens, no bridge."""
    summary, truth = drive_small_rectangle(
        tmp_path, "--ros-interface", "rmw_zenoh", "--domain-id", "7"
    )
    twist = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
    assert summary["cmd_vel_key"] == f"7/r2/cmd_vel/geometry_msgs::msg::dds_::Twist_/{twist}"
    assert summary["estimate_key"].startswith(
        "7/relloc/r2/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_"
    )
    assert summary["received"]["decode_error"] == 0 and summary["received"]["estimate"] > 100
    check_small_rectangle(summary, truth)


def test_ctrl_c_makes_navigate_send_zero_within_one_control_period(tmp_path: Path) -> None:
    """A running ``relloc navigate`` gets SIGINT: a zero Twist follows within one period."""
    from relloc.config import TeamConfig
    from relloc.events import OdometryEvent

    team = write_team(tmp_path)
    config = TeamConfig.load(team)
    port = free_tcp_port()
    session = open_session(ZenohOptions(listen=(f"tcp/127.0.0.1:{port}",), multicast=False))
    received: list[tuple[float, float, float]] = []
    lock = threading.Lock()

    def on_cmd(sample: Any) -> None:
        msg = decode(sample.payload.to_bytes(), TWIST)
        with lock:
            received.append((time.monotonic(), float(msg.linear.x), float(msg.angular.z)))

    sub = session.declare_subscriber("r2/cmd_vel", on_cmd)
    odom_pub = session.declare_publisher("r2/odom")
    pose_pub = session.declare_publisher("relloc/r2/pose")
    halt = threading.Event()
    heading = math.radians(config.robot("r2").heading_offset_deg)

    def robot_and_engine() -> None:
        # r2 stands at the first waypoint, its odometry and a converged estimate keep coming.
        x0, y0 = load_path(SMALL).waypoints[0]
        while not halt.is_set():
            t = time.time()
            odom_pub.put(encode(odometry_msg(OdometryEvent(t, "r2", 0.0, 0.0, -heading))))
            cov = [[0.003, 0.0], [0.0, 0.003]]
            pose_pub.put(encode(pose_with_covariance_msg(t - 0.1, x0, y0, cov=cov, frame_id="r0")))
            halt.wait(0.05)

    feeder = threading.Thread(target=robot_and_engine, daemon=True)
    feeder.start()
    nav = relloc(
        "navigate",
        "--config",
        str(team),
        "--robot",
        "r2",
        "--path",
        str(SMALL),
        "--settle-time",
        "0.3",
        *zenoh_args(connect=port),
        log=tmp_path / "nav.log",
    )
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with lock:
                moving = [r for r in received if r[1] != 0.0 or r[2] != 0.0]
            if len(moving) >= 3:
                break
            time.sleep(0.02)
        assert moving, "navigate never commanded motion:\n" + (tmp_path / "nav.log").read_text()
        pressed = time.monotonic()
        nav.send_signal(signal.SIGINT)
        code = nav.wait(timeout=15)
        time.sleep(0.2)
    finally:
        halt.set()
        stop(nav)
        sub.undeclare()
        session.close()
    assert code == 130, (tmp_path / "nav.log").read_text()
    with lock:
        after = [r for r in received if r[0] >= pressed]
    assert after, "no command after Ctrl-C"
    first_zero = next(r for r in after if r[1] == 0.0 and r[2] == 0.0)
    print(f"Ctrl-C to zero command on cmd_vel: {1e3 * (first_zero[0] - pressed):.1f} ms")
    assert first_zero[0] - pressed <= 0.1  # one control period at the default 10 Hz
    assert all(r[1] == 0.0 and r[2] == 0.0 for r in after if r[0] >= first_zero[0])
    log = (tmp_path / "nav.log").read_text()
    assert "interrupted" in log


@pytest.mark.slow
def test_navigate_in_process_without_serve(tmp_path: Path) -> None:
    """``relloc navigate --in-process`` runs the localizer itself: sim-robots + navigate only."""
    team = write_team(tmp_path, particles=3000)
    port = free_tcp_port()
    procs = []
    try:
        procs.append(start_sim_robots(tmp_path, team, port))
        nav = start_navigate(tmp_path, team, port, "--in-process")
        procs.append(nav)
        code = nav.wait(timeout=75)
        assert code == 0, (tmp_path / "nav.log").read_text() + (tmp_path / "sim.log").read_text()
    finally:
        for proc in reversed(procs):
            stop(proc)
    summary = json.loads((tmp_path / "nav.json").read_text())
    assert summary["completed"] is True and summary["estimate_key"] == "(in process)"
