"""Closed-loop navigation in the simulator: the paper's last experiment, reproducible.

The derivation: docs/explanation/internals.md, section ``relloc.navigation.closed_loop``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rich.console import Console
from rich.table import Table

from relloc.engine import Engine
from relloc.evaluation.metrics import ApeStats, GroundTruth, associate
from relloc.events import OdometryEvent
from relloc.methods import build_pipeline
from relloc.navigation.controller import ControllerConfig
from relloc.navigation.navigator import Navigator
from relloc.navigation.path import FloatArray, PathError, WaypointPath, load_path
from relloc.navigation.safety import SafetyConfig, StopRecord
from relloc.simulator import UwbErrorModel, nav_scenario

__all__ = [
    "DEFAULT_PATH",
    "NAV_PARTICLES",
    "NavResult",
    "default_path",
    "print_nav_table",
    "run_nav_scenario",
]

PATHS_DIR = Path(__file__).resolve().parents[3] / "configs" / "paths"

DEFAULT_PATH = WaypointPath(
    ((2.0, 2.0), (-1.0, 2.0), (-1.0, -0.6), (2.0, -0.6)),
    closed=True,
    name="rectangle",
    reference="r0",
)
"""A 3 m x 2.6 m rectangle around the static reference robot ``r0`` of the nav scenario
(``configs/paths/rectangle.toml`` holds the same path), driven counter-clockwise from the corner
nearest to where ``r2`` stands at the start; 11.2 m."""

NAV_PARTICLES = 10000
"""Particle count of the nav scenario when none is given: the closed loop runs about a minute
of simulated time and stays well under 20 s of compute at this count (the filter's default,
20 000, roughly doubles it for the same figures)."""


def default_path() -> WaypointPath:
    """The rectangle of the nav scenario (from ``configs/paths/rectangle.toml`` if present)."""
    file = PATHS_DIR / "rectangle.toml"
    return load_path(file) if file.is_file() else DEFAULT_PATH


@dataclass
class NavResult:
    """Everything one closed-loop run recorded (relative frame, data times in s)."""

    path: WaypointPath
    robot: str
    reference: str
    seed: int
    particles: int
    rate_hz: float
    t: FloatArray
    """Control ticks."""
    true_xy: FloatArray
    """True relative position of the robot at each tick."""
    feedback_xy: FloatArray
    """Position the controller used at each tick (NaN while held)."""
    command: FloatArray
    """``(v, w)`` sent at each tick."""
    modes: list[str]
    on_path: NDArray[np.bool_]
    """The robot had reached the first waypoint by this tick."""
    estimate_t: FloatArray
    estimate_xy: FloatArray
    estimate_truth: FloatArray
    estimate_std: FloatArray
    gt_t: FloatArray
    gt_xy: FloatArray
    """True relative trajectory at the ground-truth rate (20 Hz)."""
    start_time: float
    """When the safety gate first released the robot (NaN: never)."""
    path_start_time: float
    """When the robot reached the first waypoint (NaN: never)."""
    end_time: float
    """When the path was complete, or the last tick."""
    completed: bool
    stops: list[StopRecord]
    compute_s: float
    sim_duration: float
    localizer_stats: dict[str, int] = field(default_factory=dict)

    # ---------------------------------------------------------------- figures
    def ape_errors(self) -> FloatArray:
        """APE of every estimate of the robot while it navigated."""
        if not math.isfinite(self.start_time):
            return np.zeros(0)
        keep = (self.estimate_t >= self.start_time) & (self.estimate_t <= self.end_time)
        return np.linalg.norm(self.estimate_xy[keep] - self.estimate_truth[keep], axis=1)

    def tracking_window(self) -> NDArray[np.bool_]:
        """Ground-truth samples from reaching the first waypoint to completing the path."""
        if not math.isfinite(self.path_start_time):
            return np.zeros(self.gt_t.size, dtype=bool)
        return (self.gt_t >= self.path_start_time) & (self.gt_t <= self.end_time)

    def tracking_errors(self, moving_only: bool = False) -> FloatArray:
        """Distance of the true position to the planned path, over :meth:`tracking_window`."""
        keep = self.tracking_window()
        if moving_only and keep.any():
            step = np.linalg.norm(np.diff(self.gt_xy, axis=0, prepend=self.gt_xy[:1]), axis=1)
            keep &= step > 1e-3  # more than 2 cm/s at 20 Hz
        return self.path.distance(self.gt_xy[keep]) if keep.any() else np.zeros(0)

    def summary(self) -> dict[str, Any]:
        """The figures of the run (the ``navigation`` object of the demo JSON)."""
        ape = ApeStats.of(self.ape_errors())
        trk = ApeStats.of(self.tracking_errors())
        moving = ApeStats.of(self.tracking_errors(moving_only=True))
        return {
            "ape_median": _num(ape.median),
            "ape_std": _num(ape.std),
            "tracking_median": _num(trk.median),
            "tracking_std": _num(trk.std),
            "completed": bool(self.completed),
            "ape_rmse": _num(ape.rmse),
            "ape_max": _num(ape.max),
            "ape_n": ape.n,
            "tracking_rmse": _num(trk.rmse),
            "tracking_max": _num(trk.max),
            "tracking_moving_median": _num(moving.median),
            "tracking_n": trk.n,
            "robot": self.robot,
            "reference": self.reference,
            "path": self.path.name,
            "path_length_m": _num(self.path.length),
            "particles": self.particles,
            "control_rate_hz": self.rate_hz,
            "start_s": _num(self.start_time),
            "path_start_s": _num(self.path_start_time),
            "end_s": _num(self.end_time),
            "drive_s": _num(self.end_time - self.start_time),
            "stops": [
                {"t": round(s.t, 3), "reason": s.reason, "detail": s.detail, "stop": s.stopped}
                for s in self.stops
            ],
            "compute_s": round(self.compute_s, 3),
            "sim_duration_s": round(self.sim_duration, 3),
        }


def _num(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 5)


def run_nav_scenario(
    seed: int = 0,
    particles: int | None = None,
    *,
    path: WaypointPath | None = None,
    robot: str = "r2",
    controller: ControllerConfig | None = None,
    safety: SafetyConfig | None = None,
    uwb: UwbErrorModel | None = None,
    max_duration: float = 150.0,
    latency_compensation: bool = True,
    progress: Callable[[float], None] | None = None,
) -> NavResult:
    """Drive ``robot`` of the simulated nav team along ``path`` on the PF estimate.

    ``particles`` defaults to :data:`NAV_PARTICLES`; ``path`` to :func:`default_path`;
    ``controller``/``safety`` to their defaults updated with the path file's tables. The run
    ends one control period after the path is complete, or at ``max_duration`` (s of simulated
    time). ``uwb`` changes the simulated UWB errors (sensitivity studies). ``progress`` is
    called with the simulated time after every tick.
    """
    path = path or default_path()
    ctrl = (controller or ControllerConfig()).updated(path.controller, "path.controller")
    safe = (safety or SafetyConfig()).updated(path.safety, "path.safety")
    sim = nav_scenario(seed, robot=robot, duration=max_duration, uwb=uwb)
    config = sim.config.with_filter(particles=particles or NAV_PARTICLES)
    if path.reference and path.reference != config.reference:
        raise PathError(
            f"path {path.name!r} is relative to {path.reference!r}, the team's reference is "
            f"{config.reference!r}"
        )
    pipeline = build_pipeline("pf", config, seed=seed)
    nav = Navigator(
        path,
        config.robot(robot),
        controller=ctrl,
        safety=safe,
        latency_compensation=latency_compensation,
    )
    gt = GroundTruth(config.reference)
    engine = Engine([pipeline], sinks=[nav.on_estimate], truth_sinks=[gt.add])

    period = ctrl.period
    ticks: list[float] = []
    feedback: list[tuple[float, float]] = []
    commands: list[tuple[float, float]] = []
    modes: list[str] = []
    on_path: list[bool] = []
    end_time = math.nan
    wall = time.perf_counter()
    k = 0
    while True:
        k += 1
        now = round(k * period, 9)
        if now > max_duration + 1e-9:
            break
        for ev in sim.advance(now):
            engine.feed(ev)
            if isinstance(ev, OdometryEvent) and ev.robot == robot:
                nav.on_odometry(ev)
        cmd = nav.update(now)
        sim.set_command(robot, cmd.v, cmd.w)
        ticks.append(now)
        fb = nav.feedback
        feedback.append((fb.x, fb.y) if nav.driving and fb is not None else (math.nan, math.nan))
        commands.append((cmd.v, cmd.w))
        modes.append(cmd.mode)
        on_path.append(nav.follower.on_path)
        if progress is not None:
            progress(now)
        if nav.finished:
            end_time = now
            break
    engine.finish()
    compute_s = time.perf_counter() - wall
    if not math.isfinite(end_time):
        end_time = ticks[-1] if ticks else 0.0

    t = np.array(ticks)
    ref = config.reference
    true_xy = _relative_truth(sim, robot, ref, t)
    paired = associate(pipeline.estimates, gt, [robot])[robot]
    gt_t, _ = gt.trajectory(robot)
    gt_t = gt_t[gt_t <= (t[-1] if t.size else 0.0)]
    return NavResult(
        path=path,
        robot=robot,
        reference=ref,
        seed=seed,
        particles=config.filter.particles,
        rate_hz=ctrl.rate_hz,
        t=t,
        true_xy=true_xy,
        feedback_xy=np.array(feedback).reshape(-1, 2),
        command=np.array(commands).reshape(-1, 2),
        modes=modes,
        on_path=np.array(on_path, dtype=bool),
        estimate_t=paired.t,
        estimate_xy=paired.est,
        estimate_truth=paired.gt,
        estimate_std=paired.std,
        gt_t=gt_t,
        gt_xy=_relative_truth(sim, robot, ref, gt_t),
        start_time=math.nan if nav.start_time is None else nav.start_time,
        path_start_time=math.nan if nav.path_start_time is None else nav.path_start_time,
        end_time=end_time,
        completed=nav.completed,
        stops=list(nav.gate.records),
        compute_s=compute_s,
        sim_duration=float(t[-1]) if t.size else 0.0,
        localizer_stats=pipeline.stats(),
    )


def _relative_truth(sim: Any, robot: str, reference: str, t: FloatArray) -> FloatArray:
    """True position of ``robot`` relative to ``reference`` (the simulator's world axes are the
    team's shared heading frame: its heading offsets are the true initial yaws)."""
    if t.size == 0:
        return np.zeros((0, 2))
    return sim.true_poses(robot, t)[:, :2] - sim.true_poses(reference, t)[:, :2]


PAPER = {"ape_median": 0.109, "ape_std": 0.101, "tracking_median": 0.087, "tracking_std": 0.101}
"""The paper's figures for this experiment (real TurtleBots, motion capture)."""


def print_nav_table(result: NavResult, console: Console | None = None) -> None:
    """The demo table of the nav scenario: APE and tracking error next to the paper's."""
    from relloc.evaluation.report import make_console

    console = console or make_console()
    s = result.summary()
    done = "completed" if result.completed else "NOT completed"
    table = Table(
        title=(
            f"nav: {result.robot} drives the {result.path.name} ({result.path.length:.1f} m) "
            f"around {result.reference} on the pf estimate, {result.particles} particles: {done}"
        )
    )
    for col in ("error", "median", "std", "rmse", "max", "n", "paper median", "paper std"):
        table.add_column(col, justify="left" if col == "error" else "right")

    def cell(x: float | None) -> str:
        return "-" if x is None else f"{x:.3f}"

    table.add_row(
        "positioning APE (estimate vs truth)",
        cell(s["ape_median"]),
        cell(s["ape_std"]),
        cell(s["ape_rmse"]),
        cell(s["ape_max"]),
        str(s["ape_n"]),
        f"{PAPER['ape_median']:.3f}",
        f"{PAPER['ape_std']:.3f}",
    )
    table.add_row(
        "tracking error (truth to planned path)",
        cell(s["tracking_median"]),
        cell(s["tracking_std"]),
        cell(s["tracking_rmse"]),
        cell(s["tracking_max"]),
        str(s["tracking_n"]),
        f"{PAPER['tracking_median']:.3f}",
        f"{PAPER['tracking_std']:.3f}",
    )
    console.print(table)
    start = "never" if s["start_s"] is None else f"{s['start_s']:.1f} s"
    reached = "never" if s["path_start_s"] is None else f"{s['path_start_s']:.1f} s"
    stops = ", ".join(f"{x['reason']} at {x['t']:.1f} s" for x in s["stops"] if x["stop"]) or "none"
    console.print(
        f"  gate released at {start}, path reached at {reached}, end at {s['end_s']:.1f} s; "
        f"stops: {stops}; {s['compute_s']:.1f} s of compute"
    )
