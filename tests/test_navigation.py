"""Navigation on the relative estimate: path files, the path follower, the safety gate, the
control loop and the closed loop in the simulator (no Zenoh here; see test_navigation_live)."""

from __future__ import annotations

import itertools
import json
import math
import threading
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from relloc.config import RobotConfig
from relloc.estimate import Estimate
from relloc.events import OdometryEvent
from relloc.live.sim_robots import SimRobots, SimRobotsOptions, sim_team_config
from relloc.navigation.controller import Command, ControllerConfig, PathFollower
from relloc.navigation.live import DataClock, NavigationLoop
from relloc.navigation.navigator import Navigator
from relloc.navigation.path import PathError, WaypointPath, distance_to_polyline, load_path
from relloc.navigation.safety import SafetyConfig, SafetyGate
from relloc.ros.messages import encode, twist_msg

REPO = Path(__file__).resolve().parents[1]


# ============================================================================ helpers
def drive(
    follower: PathFollower,
    pose: tuple[float, float, float],
    *,
    seconds: float = 120.0,
    kick: tuple[float, float, float] | None = None,
) -> tuple[np.ndarray, list[Command]]:
    """Run the follower with perfect feedback on an ideal unicycle (1 ms integration).

    ``kick = (t, dx, dy)`` moves the robot sideways once (a disturbance). Returns the poses at
    every control tick and the commands.
    """
    x, y, yaw = pose
    period = follower.config.period
    poses, cmds = [], []
    t = 0.0
    while t < seconds:
        cmd = follower.step(x, y, yaw)
        poses.append((t, x, y, yaw, follower.on_path))
        cmds.append(cmd)
        if cmd.mode == "done":
            break
        for _ in range(round(period / 1e-3)):
            x += cmd.v * math.cos(yaw) * 1e-3
            y += cmd.v * math.sin(yaw) * 1e-3
            yaw += cmd.w * 1e-3
        t = round(t + period, 9)
        if kick is not None and abs(t - kick[0]) < 1e-9:
            x, y = x + kick[1], y + kick[2]
    return np.array(poses), cmds


def estimate(t: float, robot: str, xy: tuple[float, float], std: float = 0.05) -> Estimate:
    var = std**2
    return Estimate(t, "pf", "r0", {robot: xy}, {robot: ((var, 0.0), (0.0, var))})


def ready_navigator(path: WaypointPath, **safety: float) -> Navigator:
    """A navigator for ``r1`` (heading offset 0) with a quick gate."""
    cfg = SafetyConfig(**{"settle_time": 0.2, "max_age": 0.5, "max_std": 0.2, **safety})
    return Navigator(path, RobotConfig(name="r1"), safety=cfg)


def feed_until(
    nav: Navigator, t_end: float, *, t_start: float = 0.0, estimates: bool = True
) -> list[Command]:
    """Odometry at 20 Hz (robot standing at the origin of its odometry, on the path's first
    waypoint) and estimates at 10 Hz; a control tick every 0.1 s. Returns the commands."""
    cmds = []
    k0, k1 = round(t_start / 0.05), round(t_end / 0.05)
    for k in range(k0 + 1, k1 + 1):
        t = k * 0.05
        nav.on_odometry(OdometryEvent(t, "r1", 0.0, 0.0, 0.0))
        if k % 2 == 0:
            if estimates:
                nav.on_estimate(estimate(t - 0.1, "r1", (0.0, 0.0)))
            cmds.append(nav.update(t))
    return cmds


STRAIGHT = WaypointPath(((0.0, 0.0), (4.0, 0.0)), name="straight")
SQUARE = WaypointPath(((0.0, 0.0), (2.0, 0.0), (2.0, 1.5), (0.0, 1.5)), closed=True, name="square")


# ============================================================================ path files
def test_example_path_files_load() -> None:
    for file in sorted((REPO / "configs" / "paths").glob("*.toml")):
        path = load_path(file)
        assert len(path.waypoints) >= 2 and path.length > 0


def test_path_file_with_fewer_than_two_waypoints_is_a_clear_error(tmp_path: Path) -> None:
    file = tmp_path / "one.toml"
    file.write_text("waypoints = [[1.0, 2.0]]\n")
    with pytest.raises(PathError, match=r"one\.toml: a path needs at least two waypoints, got 1"):
        load_path(file)
    file.write_text("waypoints = []\n")
    with pytest.raises(PathError, match="at least two waypoints, got 0"):
        load_path(file)
    file.write_text('name = "x"\n')
    with pytest.raises(PathError, match="no 'waypoints'"):
        load_path(file)


def test_path_file_with_non_numeric_values_is_a_clear_error(tmp_path: Path) -> None:
    file = tmp_path / "bad.toml"
    file.write_text('waypoints = [[0.0, 0.0], [1.0, "two"]]\n')
    with pytest.raises(PathError, match=r"waypoints\[1\]\[1\]: expected a number, got 'two'"):
        load_path(file)
    file.write_text("waypoints = [[0.0, 0.0], [true, 1.0]]\n")
    with pytest.raises(PathError, match=r"waypoints\[1\]\[0\]: expected a number, got True"):
        load_path(file)
    file.write_text("waypoints = [[0.0, 0.0], [1.0, nan]]\n")
    with pytest.raises(PathError, match=r"waypoints\[1\]\[1\]: expected a finite number"):
        load_path(file)
    file.write_text("waypoints = [[0.0, 0.0], [1.0, 2.0, 3.0]]\n")
    with pytest.raises(PathError, match=r"waypoints\[1\]: expected a pair"):
        load_path(file)
    file.write_text("waypoints = [[0.0, 0.0], [1.0, 1.0]]\nspeed = 3\n")
    with pytest.raises(PathError, match=r"unknown key\(s\) \['speed'\]"):
        load_path(file)
    file.write_text("waypoints = [[0.0, 0.0], [1.0, 1.0]\n")
    with pytest.raises(PathError, match="not valid TOML"):
        load_path(file)
    with pytest.raises(PathError, match="path file not found"):
        load_path(tmp_path / "missing.toml")


def test_bad_path_file_is_one_line_from_the_cli(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from relloc.cli import main

    file = tmp_path / "bad.toml"
    file.write_text('waypoints = [[0.0, "a"], [1.0, 1.0]]\n')
    code = main(
        [
            "navigate",
            "--config",
            str(REPO / "configs/tiers/pair_range_20220907_1725.toml"),
            "--robot",
            "x",
            "--path",
            str(file),
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.count("\n") == 0 and "waypoints[0][1]: expected a number, got 'a'" in err


def test_navigate_refuses_the_reference_robot_and_a_foreign_path(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from relloc.cli import main
    from relloc.simulator import nav_scenario

    team = tmp_path / "team.toml"
    sim_team_config(nav_scenario(0, duration=5.0)).save(team)
    rect = str(REPO / "configs/paths/rectangle.toml")
    assert main(["navigate", "--config", str(team), "--robot", "r0", "--path", rect]) == 2
    assert "r0 is the reference robot" in capsys.readouterr().err
    assert main(["navigate", "--config", str(team), "--robot", "r9", "--path", rect]) == 2
    assert "unknown robot 'r9'" in capsys.readouterr().err
    other = tmp_path / "other.toml"
    other.write_text('reference = "turtle04"\nwaypoints = [[0, 0], [1, 0]]\n')
    assert main(["navigate", "--config", str(team), "--robot", "r2", "--path", str(other)]) == 2
    assert "relative to 'turtle04'" in capsys.readouterr().err


def test_path_controller_overrides_are_validated(tmp_path: Path) -> None:
    file = tmp_path / "p.toml"
    file.write_text("waypoints = [[0, 0], [1, 0]]\n[controller]\nmax_v = 0.1\nbogus = 1\n")
    path = load_path(file)
    assert path.waypoints == ((0.0, 0.0), (1.0, 0.0))
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['bogus'\]"):
        ControllerConfig().updated(path.controller)
    assert ControllerConfig().updated({"max_v": 0.1}).max_v == 0.1
    with pytest.raises(ValueError, match="positive"):
        ControllerConfig(max_v=0.0)


def test_distance_to_polyline() -> None:
    square = SQUARE.points
    d = distance_to_polyline([[1.0, 0.0], [1.0, 0.5], [3.0, 0.0], [-1.0, 2.5]], square)
    np.testing.assert_allclose(d, [0.0, 0.5, 1.0, math.sqrt(2.0)])
    assert SQUARE.length == pytest.approx(7.0)


# ============================================================================ the follower
def test_follower_converges_onto_a_straight_path() -> None:
    cfg = ControllerConfig()
    # Start on the first waypoint heading 40 degrees off, and get kicked 0.3 m sideways at 5 s.
    poses, cmds = drive(
        PathFollower(STRAIGHT, cfg), (0.0, 0.0, math.radians(40)), kick=(5.0, 0.0, 0.3)
    )
    assert cmds[-1].mode == "done"
    t, x, y = poses[:, 0], poses[:, 1], poses[:, 2]
    assert math.hypot(x[-1] - 4.0, y[-1]) < 2 * cfg.goal_tolerance
    kicked = np.flatnonzero(t >= 5.0)[0]
    assert abs(y[kicked]) > 0.25
    # Back within 2 cm of the line after 1.5 m of travel, and it stays there.
    later = x > x[kicked] + 1.5
    assert later.any() and np.max(np.abs(y[later])) < 0.02
    # Converged without overshooting much to the other side.
    assert np.min(y[kicked:]) > -0.05
    assert all(abs(c.v) <= cfg.max_v + 1e-12 and abs(c.w) <= cfg.max_w + 1e-12 for c in cmds)


def test_follower_corners_a_rectangle_with_perfect_feedback() -> None:
    cfg = ControllerConfig()
    follower = PathFollower(SQUARE, cfg)
    poses, cmds = drive(follower, (0.0, 0.0, 0.0))
    assert follower.done and cmds[-1].mode == "done"
    errors = SQUARE.distance(poses[:, 1:3])
    assert np.median(errors) < 0.005 and errors.max() < 0.03
    # It turned in place at the three corners (not at the end, where it stops).
    turns = sum(1 for a, b in itertools.pairwise(cmds) if b.mode == "rotate" and a.mode != "rotate")
    assert turns == 3
    assert all(c.v == 0.0 for c in cmds if c.mode == "rotate")
    assert all(abs(c.v) <= cfg.max_v + 1e-12 and abs(c.w) <= cfg.max_w + 1e-12 for c in cmds)
    # Driving 7 m at 0.25 m/s, slowing for corners and turning 3 x 90 degrees: under a minute.
    assert poses[-1, 0] < 60.0


def test_follower_approaches_the_first_waypoint_from_elsewhere() -> None:
    follower = PathFollower(SQUARE)
    poses, cmds = drive(follower, (-1.0, -0.8, math.pi))
    assert follower.done
    assert cmds[0].mode == "rotate"  # facing away: turn in place first
    on_path = poses[:, 4].astype(bool)
    assert not on_path[0] and on_path[-1]
    # It reached the first waypoint, and from then on it stays on the path.
    started = np.flatnonzero(on_path)[0]
    assert math.hypot(*poses[started, 1:3]) < 0.05
    assert SQUARE.distance(poses[started:, 1:3]).max() < 0.03


def test_command_limits_hold_for_a_tight_turn() -> None:
    cfg = ControllerConfig(
        max_v=0.3, max_w=0.4, rotate_threshold_deg=80.0, align_tolerance_deg=10.0
    )
    path = WaypointPath(((0.0, 0.0), (3.0, 0.0)))
    _, cmds = drive(PathFollower(path, cfg), (0.0, 0.05, math.radians(70)))
    assert max(abs(c.w) for c in cmds) <= 0.4 + 1e-12
    assert max(abs(c.v) for c in cmds) <= 0.3 + 1e-12


# ============================================================================ safety
def test_gate_waits_for_a_converged_estimate_before_starting() -> None:
    gate = SafetyGate(SafetyConfig(settle_time=1.0, max_std=0.2), "r1")
    assert gate.evaluate(0.0, None, 0.0) == "no_estimate"
    assert gate.evaluate(0.1, estimate(0.05, "r1", (0, 0), std=1.5), 0.1) == "uncertain"
    assert gate.evaluate(0.2, estimate(0.15, "r1", (0, 0)), 0.2) == "uncertain"  # not settled yet
    assert gate.evaluate(1.15, estimate(1.1, "r1", (0, 0)), 1.15) == "uncertain"
    assert gate.evaluate(1.2, estimate(1.15, "r1", (0, 0)), 1.2) is None
    assert [r.reason for r in gate.records] == ["uncertain", "released"]


def test_gate_starts_below_start_std_and_stops_above_max_std() -> None:
    """Hysteresis: an estimate that just passes the stop bound does not start the robot."""
    gate = SafetyGate(SafetyConfig(settle_time=0.0, max_std=0.2, start_std=0.1), "r1")
    assert gate.evaluate(0.0, estimate(0.0, "r1", (0, 0), std=0.15), 0.0) == "uncertain"
    assert "0.150 m > 0.1 m" in gate.records[-1].detail
    assert gate.evaluate(0.1, estimate(0.1, "r1", (0, 0), std=0.09), 0.1) is None
    assert (
        gate.evaluate(0.2, estimate(0.2, "r1", (0, 0), std=0.15), 0.2) is None
    )  # moving: 0.2 holds
    assert gate.evaluate(0.3, estimate(0.3, "r1", (0, 0), std=0.25), 0.3) == "uncertain"
    assert gate.evaluate(0.4, estimate(0.4, "r1", (0, 0), std=0.15), 0.4) == "uncertain"
    assert [r.reason for r in gate.records] == ["uncertain", "released", "uncertain"]


def test_gate_holds_on_an_unobservable_orientation_or_a_minor_mode() -> None:
    gate = SafetyGate(SafetyConfig(settle_time=0.0, max_std=5.0), "r1")
    ring = replace(estimate(0.0, "r1", (0, 0)), orientation_observable=False)
    assert gate.evaluate(0.0, ring, 0.0) == "unobservable"
    assert "drive any robot" in gate.records[-1].detail
    split = replace(estimate(0.1, "r1", (0, 0)), mode_weight=0.7, n_modes=2)
    assert gate.evaluate(0.1, split, 0.1) == "modes"
    dominant = replace(estimate(0.2, "r1", (0, 0)), mode_weight=0.95, n_modes=2)
    assert gate.evaluate(0.2, dominant, 0.2) is None
    assert [r.reason for r in gate.records] == ["unobservable", "modes", "released"]


def test_stale_estimate_stops_the_robot_within_one_control_period(
    caplog: pytest.LogCaptureFixture,
) -> None:
    nav = ready_navigator(STRAIGHT, max_age=0.5)
    cmds = feed_until(nav, 3.0)
    assert not cmds[-1].is_zero and cmds[-1].mode in ("track", "rotate")
    last_estimate_t = nav.estimate.t if nav.estimate else math.nan
    caplog.set_level("WARNING", logger="relloc.navigation")
    cmds = feed_until(nav, 4.0, t_start=3.0, estimates=False)
    ticks = np.arange(3.1, 4.0 + 1e-9, 0.1)
    stale = ticks - last_estimate_t > 0.5
    first = int(np.flatnonzero(stale)[0])
    assert all(not c.is_zero for c in cmds[:first])  # still fresh: still driving
    assert all(c.is_zero and c.reason == "stale_estimate" for c in cmds[first:])
    # The first stale tick is at most one control period after the estimate became stale.
    assert ticks[first] - (last_estimate_t + 0.5) <= 0.1 + 1e-9
    assert nav.gate.records[-1].reason == "stale_estimate"
    assert "stale_estimate" in caplog.text


def test_high_covariance_stops_the_robot_at_the_next_tick() -> None:
    nav = ready_navigator(STRAIGHT)
    cmds = feed_until(nav, 3.0)
    assert not cmds[-1].is_zero
    nav.on_odometry(OdometryEvent(3.05, "r1", 0.0, 0.0, 0.0))
    nav.on_estimate(estimate(3.0, "r1", (0.0, 0.0), std=0.6))  # diverged
    cmd = nav.update(3.1)
    assert cmd.is_zero and cmd.reason == "uncertain"
    # It resumes only after the estimate has been good again for the settle time.
    cmds = feed_until(nav, 3.2, t_start=3.1)
    assert cmds[-1].is_zero
    cmds = feed_until(nav, 4.0, t_start=3.2)
    assert not cmds[-1].is_zero
    reasons = [r.reason for r in nav.gate.records]
    assert reasons[-3:] == ["released", "uncertain", "released"]


def test_missing_or_stale_odometry_stops_the_robot() -> None:
    nav = ready_navigator(STRAIGHT)
    nav.on_estimate(estimate(0.0, "r1", (0.0, 0.0)))
    assert nav.update(0.1).reason == "no_odometry"
    cmds = feed_until(nav, 2.0)
    assert not cmds[-1].is_zero
    nav.on_estimate(estimate(2.5, "r1", (0.0, 0.0)))  # estimates keep coming, odometry does not
    assert nav.update(2.6).reason == "stale_odometry"


def test_interrupt_is_terminal() -> None:
    nav = ready_navigator(STRAIGHT)
    cmds = feed_until(nav, 2.0)
    assert not cmds[-1].is_zero
    assert nav.interrupt(2.0).is_zero
    assert all(c.is_zero and c.reason == "interrupted" for c in feed_until(nav, 3.0, t_start=2.0))
    assert nav.finished and not nav.completed


def test_latency_compensation_moves_the_estimate_by_odometry() -> None:
    nav = ready_navigator(STRAIGHT)
    feed_until(nav, 1.0)
    # The robot drove 0.2 m along x since the estimate's time (odometry), the estimate lags.
    nav.on_odometry(OdometryEvent(1.05, "r1", 0.1, 0.0, 0.0, v=2.0))
    nav.on_odometry(OdometryEvent(1.1, "r1", 0.2, 0.0, 0.0, v=2.0))
    nav.on_estimate(estimate(1.0, "r1", (0.5, 0.1)))
    nav.update(1.1)
    assert nav.feedback is not None
    assert (nav.feedback.x, nav.feedback.y) == pytest.approx((0.5 + 0.2, 0.1))


# ============================================================================ control loop
class _Recorder:
    def __init__(self) -> None:
        self.sent: list[tuple[float, float, float]] = []
        self.lock = threading.Lock()
        self.fresh = threading.Event()
        """Set at every command (for a test to act just after one, while the loop waits)."""

    def __call__(self, v: float, w: float) -> None:
        with self.lock:
            self.sent.append((time.monotonic(), v, w))
        self.fresh.set()


def _loop_with_live_data(nav: Navigator) -> tuple[NavigationLoop, _Recorder, threading.Event]:
    """A loop at 20 Hz whose data keep coming (a feeder thread), like a live robot's."""
    nav.follower.config = ControllerConfig(rate_hz=20.0)
    clock = DataClock()
    rec = _Recorder()
    loop = NavigationLoop(nav, rec, clock.now)
    stop_feed = threading.Event()

    def feeder() -> None:
        while not stop_feed.is_set():
            t = time.time()
            with loop.lock:
                nav.on_odometry(OdometryEvent(t, "r1", 0.0, 0.0, 0.0))
                nav.on_estimate(estimate(t, "r1", (0.0, 0.0)))
            clock.observe(t)
            stop_feed.wait(0.02)

    threading.Thread(target=feeder, daemon=True).start()
    return loop, rec, stop_feed


def test_ctrl_c_stops_the_robot_within_one_control_period() -> None:
    nav = ready_navigator(STRAIGHT)
    loop, rec, stop_feed = _loop_with_live_data(nav)
    stop = threading.Event()
    result: list[str] = []
    runner = threading.Thread(target=lambda: result.append(loop.run(stop)))
    runner.start()
    try:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and not any(v != 0.0 for _, v, _ in rec.sent):
            time.sleep(0.01)
        assert any(v != 0.0 for _, v, _ in rec.sent), "the robot never started"
        # Press just after a command, while the loop waits for its next tick: pressed during a
        # tick, the command that tick computed would still go out after the press.
        rec.fresh.clear()
        assert rec.fresh.wait(5.0)
        pressed = time.monotonic()
        stop.set()  # what the SIGINT handler of relloc navigate does
        runner.join(timeout=2.0)
    finally:
        stop_feed.set()
    assert result == ["interrupted"]
    after = [(t, v, w) for t, v, w in rec.sent if t >= pressed]
    assert after and after[0][1:] == (0.0, 0.0)
    assert after[0][0] - pressed <= loop.period
    assert all((v, w) == (0.0, 0.0) for _, v, w in after)
    assert nav.gate.records[-1].reason == "interrupted"


def test_keyboard_interrupt_in_the_loop_sends_zero() -> None:
    nav = ready_navigator(STRAIGHT)
    loop, rec, stop_feed = _loop_with_live_data(nav)
    real_now = loop.now
    calls = {"n": 0}

    def now() -> float | None:
        calls["n"] += 1
        if calls["n"] == 30:  # Ctrl-C lands while the loop runs
            raise KeyboardInterrupt
        return real_now()

    loop.now = now
    try:
        assert loop.run() == "interrupted"
    finally:
        stop_feed.set()
    assert any(v != 0.0 for _, v, _ in rec.sent[:-3])
    assert all((v, w) == (0.0, 0.0) for _, v, w in rec.sent[-3:])


def test_data_clock_follows_the_robots_clock() -> None:
    wall = {"t": 100.0}
    clock = DataClock(rate=2.0, wall=lambda: wall["t"])
    assert clock.now() is None
    clock.observe(5000.0)
    wall["t"] += 0.25
    assert clock.now() == pytest.approx(5000.5)
    clock.observe(4999.0)  # an older stamp does not move the clock back
    assert clock.now() == pytest.approx(5000.5)


# ============================================================================ simulated robots
def test_sim_robots_obey_cmd_vel_and_stop_without_it() -> None:
    from relloc.simulator import nav_scenario

    sim = nav_scenario(0, duration=10.0)
    config = sim_team_config(sim, particles=500)
    assert config.robot("r2").cmd_vel_topic == "/r2/cmd_vel" and config.filter.particles == 500
    robots = SimRobots(sim, config, session=None, options=SimRobotsOptions(cmd_timeout=0.5))
    assert robots.cmd_keys == {"r2": "r2/cmd_vel"}
    assert robots.odom_keys["r1"] == "r1/odom"
    sample = SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: encode(twist_msg(0.2, 0.0))))
    start = sim.true_pose("r2", 0.0)
    for k in range(1, 21):  # 1 s with the command repeated at 10 Hz, as relloc navigate does
        if k % 2 == 1:
            robots._on_cmd("r2", sample)
        robots._apply_commands((k - 1) * 0.05)
        sim.advance(k * 0.05)
        robots.t_sim = k * 0.05
    moved = math.dist(sim.true_pose("r2", 1.0)[:2], start[:2])
    assert moved == pytest.approx(0.2, abs=0.03)  # actuation noise is 5 %
    # No more commands: within cmd_timeout (0.5 s) the robot stops, as a robot base does.
    for k in range(21, 41):
        robots._apply_commands((k - 1) * 0.05)
        sim.advance(k * 0.05)
    assert robots.sim._runner.commands["r2"] == (0.0, 0.0)
    p1, p2 = sim.true_pose("r2", 1.6), sim.true_pose("r2", 2.0)
    assert math.dist(p1[:2], p2[:2]) == 0.0


def test_sim_robots_stamp_on_a_whole_second_so_every_run_batches_alike() -> None:
    """The default time base is a whole second of wall time: the stamps' phase on the
    localizer's batch grid (absolute stamps, 0.1 s cells) is the same from run to run."""
    from relloc.simulator import nav_scenario

    sim = nav_scenario(0, duration=10.0)
    robots = SimRobots(
        sim, sim_team_config(sim), session=None, options=SimRobotsOptions(rate=50.0, duration=0.2)
    )
    sent: list[tuple[object, bytes]] = []
    robots._pubs = SimpleNamespace(  # type: ignore[assignment]
        wait_matching=lambda *a: False, put=lambda *a: sent.append(a), close=lambda: None
    )
    summary = robots.run()
    assert robots.time_base == math.floor(robots.time_base) and sent
    stamps = np.array([p[0] for p in summary["truth"]["r2"]]) - robots.time_base
    assert np.allclose(stamps, np.round(stamps / 0.05) * 0.05, atol=1e-6)


# ============================================================================ closed loop
def test_closed_loop_in_the_simulator_drives_a_small_rectangle() -> None:
    from relloc.navigation.closed_loop import run_nav_scenario

    path = load_path(REPO / "configs" / "paths" / "small_rectangle.toml")
    result = run_nav_scenario(0, 3000, path=path, max_duration=60.0)
    s = result.summary()
    assert s["completed"] is True
    assert s["tracking_median"] < 0.15 and s["ape_median"] < 0.2
    # The gate held the robot while the formation's orientation was unobservable (the team
    # has just started to move) and until the estimate had converged, then released it once.
    assert [x["reason"] for x in s["stops"]] == [
        "unobservable",
        "uncertain",
        "released",
        "goal reached",
    ]
    first_move = result.t[np.flatnonzero(np.any(result.command != 0.0, axis=1))[0]]
    assert first_move == pytest.approx(result.start_time)
    assert s["start_s"] is not None and s["start_s"] > 1.0


def test_demo_reports_the_nav_scenario(tmp_path: Path) -> None:
    from relloc.evaluation.report import make_console
    from relloc.runs.demo import DemoOptions, run_demo

    opts = DemoOptions(
        seed=0,
        particles=2000,
        scenarios=("nav",),
        out=tmp_path,
        json_path=tmp_path / "demo.json",
        progress=False,
    )
    console = make_console()
    with console.capture() as captured:
        results = run_demo(opts, console)
    nav = results["scenarios"]["nav"]["navigation"]
    for key in ("ape_median", "ape_std", "tracking_median", "tracking_std"):
        assert isinstance(nav[key], float) and 0.0 < nav[key] < 0.5
    assert nav["completed"] is True
    on_disk = json.loads((tmp_path / "demo.json").read_text())
    assert on_disk["scenarios"]["nav"]["navigation"]["completed"] is True
    assert (tmp_path / "nav_path.png").stat().st_size > 10_000
    assert "tracking error" in captured.get() and "positioning APE" in captured.get()
