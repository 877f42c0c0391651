"""A flying team: quadrotors on smooth 3D paths (``drones``, ``drones_uwb``, ``drones_six``).

:class:`FlightSimulation` is a :class:`~relloc.simulator.runner.Simulation` whose robots follow
closed-form paths (:class:`FlightPath`: a Lissajous figure in x-y, a slow bob in z, a yaw of its
own, for a quadrotor is holonomic) and whose events are 3D:

* ground truth ``(x, y, z)`` and yaw in the world frame at 20 Hz;
* UWB ranges at 10 Hz between every two drones' tags (no intra-drone pair): the 3D distance of
  the tags at their 3D lever arms plus the pair's bias, drawn as the 2D scenarios draw them
  (:func:`~relloc.simulator.schedules.draw_uwb`), plus white noise and NLOS spikes
  (:data:`DRONE_UWB`); or, ``range_average`` set, each range the mean true distance over the
  past ``range_average`` seconds (a LinkTrack's averaged output, ``drones_six``);
* velocity odometry at 20 Hz in each drone's own odometry frame (its start pose, z from its
  start height): the body-frame velocity, scaled horizontally by the drone's scale factor, with
  white noise on each axis, and the yaw rate with the drone's gyro bias and noise, integrated
  (:class:`FlightOdometryModel`);
* a downward range finder's height at 10 Hz (:class:`HeightSensorModel`).

The true pair biases, heading offsets (initial yaws), scales and gyro biases are the
:class:`Simulation` attributes; :attr:`FlightSimulation.lever_arms` holds the 3D arms and
:meth:`FlightSimulation.true_positions` the 3D truth. Every draw has its own seeded stream, so
the same seed gives the same events, ``drones_uwb`` flies exactly as ``drones`` does, and no
other scenario draws anything different.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from operator import attrgetter
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from relloc import geometry
from relloc.config import TagConfig
from relloc.events import Event, GroundTruthEvent, HeightEvent, OdometryEvent, RangeEvent
from relloc.odometry import wrap_angle
from relloc.sensors.registry import registered
from relloc.simulator.error_models import OdometryErrorModel, UwbErrorModel
from relloc.simulator.kinematics import RobotMotion, accumulate
from relloc.simulator.runner import Simulation, _Runner, _window
from relloc.simulator.streams import stream

__all__ = [
    "DRONE_AREA",
    "DRONE_PATHS",
    "DRONE_TAG_ARMS",
    "DRONE_UWB",
    "HEIGHT_SENSOR",
    "SIX_TAG_ARMS",
    "SIX_TAG_UWB",
    "Drone",
    "FlightOdometryModel",
    "FlightPath",
    "FlightSimulation",
    "HeightSensorModel",
    "drones_scenario",
    "drones_six_scenario",
    "drones_uwb_scenario",
]

FloatArray = NDArray[np.float64]
Arm = tuple[float, float, float]


@dataclass(frozen=True)
class FlightPath:
    """A smooth 3D path: ``p = centre + amplitude * sin(omega * t + phase)`` per axis, and
    ``yaw = yaw0 + spin * t + swing * (sin(omega_yaw * t + phase_yaw) - sin(phase_yaw))``.

    The horizontal speed is at most ``hypot(ax * wx, ay * wy)``; the yaw does not follow the
    velocity."""

    centre: tuple[float, float, float]
    amplitude: tuple[float, float, float]
    omega: tuple[float, float, float]
    """Angular frequency of each axis (rad/s)."""
    spin: float
    swing: float
    omega_yaw: float
    phase: tuple[float, float, float] = (0.0, 0.0, 0.0)
    phase_yaw: float = 0.0
    yaw0: float = 0.0

    def evaluate(self, t: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """World positions ``(n, 3)`` and unwrapped yaws ``(n,)`` at times ``t``."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        angle = np.multiply.outer(t, self.omega) + np.asarray(self.phase)
        pos = np.asarray(self.centre) + np.asarray(self.amplitude) * np.sin(angle)
        wobble = np.sin(self.omega_yaw * t + self.phase_yaw) - math.sin(self.phase_yaw)
        return pos, self.yaw0 + self.spin * t + self.swing * wobble


@dataclass(frozen=True)
class Drone:
    """One quadrotor: its name, path and UWB tags ``(node, 3D lever arm in the body frame)``."""

    name: str
    path: FlightPath
    tags: tuple[tuple[str, Arm], ...]


@dataclass(frozen=True)
class FlightOdometryModel(OdometryErrorModel):
    """A flying robot's velocity odometry (VIO, optical flow): per sample
    ``(vx, vy)_m = scale * (vx, vy) + N(0, sigma_v^2)`` in the body frame,
    ``vz_m = vz + N(0, sigma_vz^2)``, ``w_m = w + gyro_bias + N(0, sigma_w^2)``, always (a
    flying robot never rests); the scale and the gyro bias are drawn as for ground robots."""

    sigma_vz: float = 0.005
    """Vertical speed noise per sample (m/s)."""


@dataclass(frozen=True)
class HeightSensorModel:
    """A downward range finder: the body's height above the ground plus ``N(0, sigma^2)``."""

    rate_hz: float = 10.0
    sigma: float = 0.04


HEIGHT_SENSOR = HeightSensorModel()
"""The drones' height sensor: 10 Hz, 4 cm."""


DRONE_UWB = UwbErrorModel(orientation_amplitude=0.0)
"""The drones' UWB: the tag scenarios' rate, noise, bias draws, NLOS spikes and dropouts,
without the ground robots' body-occlusion (heading) term: a drone's tags sit clear of its
body, above it (pass ``uwb=`` to add the term back)."""


class FlightSimulation(Simulation):
    """A :class:`Simulation` of flying robots: 3D paths, 3D tag arms, heights (module docstring).

    ``motions`` keep each drone's start pose and the horizontal part of its arms; the config
    (``dimension = 3``) and :attr:`lever_arms` the 3D arms. Detections are not simulated.
    """

    def __init__(
        self,
        drones: Sequence[Drone],
        *,
        reference: str,
        seed: int = 0,
        duration: float = 60.0,
        name: str = "sim_flight",
        area: tuple[float, float, float, float],
        uwb: UwbErrorModel = DRONE_UWB,
        odometry: FlightOdometryModel | None = None,
        height: HeightSensorModel | None = None,
        odometry_topics: bool = True,
        range_average: float = 0.0,
    ) -> None:
        """``height`` None: no height sensor; ``odometry_topics`` False: no odometry;
        ``range_average`` > 0: each range is the mean distance over that many seconds before
        its stamp (else the distance at its stamp less the model's latency)."""
        self.range_average = float(range_average)
        self.flights = {d.name: d.path for d in drones}
        self.lever_arms: dict[str, Arm] = {n: arm for d in drones for n, arm in d.tags}
        self.flight_odometry = odometry or FlightOdometryModel()
        self.height_model = height
        motions = []
        for d in drones:
            pos, yaw = d.path.evaluate(0.0)
            flat = tuple((n, (a[0], a[1])) for n, a in d.tags)
            x0, y0, yaw0 = float(pos[0, 0]), float(pos[0, 1]), float(yaw[0])
            motions.append(RobotMotion(d.name, d.tags[0][0], x0, y0, yaw0, tags=flat))
        super().__init__(
            motions,
            reference=reference,
            seed=seed,
            duration=duration,
            name=name,
            uwb=uwb,
            odometry=self.flight_odometry,
            area=area,
            odometry_topics=odometry_topics,
        )
        for robot, od in self._odom.items():
            od["ny"] = stream(self.seed, "odom-vy", robot).standard_normal(od["t"].size)
            od["nz"] = stream(self.seed, "odom-vz", robot).standard_normal(od["t"].size)
        self._heights: dict[str, tuple[FloatArray, FloatArray]] = {}  # times, noise
        if height is not None:
            period = 1.0 / height.rate_hz
            for robot in self.robots:
                phase = stream(self.seed, "height-time", robot).uniform(0.0, period)
                times = np.arange(phase, self.duration + 1e-9, period)
                noise = stream(self.seed, "height-noise", robot).standard_normal(times.size)
                self._heights[robot] = (times, noise * height.sigma)
        robots = tuple(
            replace(
                r,
                tags=tuple(TagConfig(t.node, self.lever_arms[t.node]) for t in r.tags),
                height_topic=f"/{r.name}/height" if height else "",  # its range finder's
                height_sigma=height.sigma if height else r.height_sigma,
            )
            for r in self.config.robots
        )
        # the config states the simulated sensor's white noise (the 2D scenarios' default also
        # covers their heading-dependent term, which drones do not have)
        # an averaged range measures the geometry half its window before its stamp, as the
        # driver's data sheet would say
        uwb_config = replace(
            self.config.uwb,
            sigma=uwb.sigma,
            los_sigma=uwb.sigma,
            range_delay=self.range_average / 2.0,
        )
        self.config = replace(self.config, robots=robots, dimension=3, uwb=uwb_config)
        self._runner = _FlightRunner(self)

    def events(self) -> Iterator[Event]:
        """All events of the run, time-ordered, from a fresh start (in chunks of 5 s)."""
        runner = _FlightRunner(self)
        t = 0.0
        while t < self.duration:
            t = min(t + 5.0, self.duration)
            yield from runner.advance(t)

    def true_positions(self, robot: str, t: ArrayLike) -> FloatArray:
        """True world positions ``(n, 3)`` of ``robot`` at times ``t``."""
        return self.flights[robot].evaluate(t)[0]

    def true_poses(self, robot: str, t: ArrayLike) -> FloatArray:
        """True horizontal poses ``(n, 3)``: ``x, y, yaw`` (yaw in [-pi, pi))."""
        pos, yaw = self.flights[robot].evaluate(t)
        return np.column_stack([pos[:, :2], wrap_angle(yaw)])

    def range_error(self, robot_a: str, robot_b: str, t: ArrayLike) -> FloatArray:
        """Deterministic part of the UWB error of the first tag pair of two drones."""
        for pair in self._uwb:
            if {pair.robot_a, pair.robot_b} == {robot_a, robot_b}:
                return pair.bias + pair.orientation_term(
                    _pose(self, pair.robot_a, t), _pose(self, pair.robot_b, t)
                )
        raise KeyError(f"no UWB pair {robot_a!r}-{robot_b!r}")


def _pose(sim: FlightSimulation, robot: str, t: ArrayLike) -> tuple[FloatArray, ...]:
    """``(x, y, unwrapped yaw)`` arrays, as :meth:`UwbPair.orientation_term` takes them."""
    pos, yaw = sim.flights[robot].evaluate(t)
    return pos[:, 0], pos[:, 1], yaw


class _FlightRunner(_Runner):
    """One run of a :class:`FlightSimulation`: how far it got and the odometry integrators."""

    sim: FlightSimulation

    def __init__(self, sim: FlightSimulation) -> None:
        super().__init__(sim)
        # Per robot: last odometry time, true (x, y, z, unwrapped yaw) then, odometry pose
        # (x, y, z, unwrapped yaw) then; the odometry frame is the start pose.
        for robot, path in sim.flights.items():
            pos, yaw = path.evaluate(0.0)
            self.odom_state[robot] = (0.0, *pos[0].tolist(), float(yaw[0]), 0.0, 0.0, 0.0, 0.0)

    def advance(self, t_until: float) -> list[Event]:
        t_until = min(float(t_until), self.sim.duration)
        if t_until <= self.t_done:
            return []
        t0 = self.t_done
        out: list[Event] = []
        self._ground_truth(t0, t_until, out)
        self._odometry(t0, t_until, out)
        self._height(t0, t_until, out)
        self._ranges(t0, t_until, out)
        for plugin in registered():
            out += plugin.simulate(self.sim, t0, t_until)
        out.sort(key=attrgetter("t"))
        self.t_done = self.t_sim = t_until
        return out

    def _ground_truth(self, t0: float, t1: float, out: list[Event]) -> None:
        times = _window(self.sim._gt_times, t0, t1)
        if times.size == 0:
            return
        for robot, path in self.sim.flights.items():
            pos, yaw = path.evaluate(times)
            out.extend(
                GroundTruthEvent(t, robot, tuple(p), th)
                for t, p, th in zip(
                    times.tolist(), pos.tolist(), wrap_angle(yaw).tolist(), strict=True
                )
            )

    def _odometry(self, t0: float, t1: float, out: list[Event]) -> None:
        sim, om = self.sim, self.sim.flight_odometry
        if not sim.odometry_topics:
            return
        for robot, path in sim.flights.items():
            od = sim._odom[robot]
            i0, i1 = np.searchsorted(od["t"], [t0, t1], side="right")
            if i1 <= i0:
                continue
            times = od["t"][i0:i1]
            t_last, x, y, z, yaw_last, ox, oy, oz, oyaw = self.odom_state[robot]
            pos, yaw = path.evaluate(times)
            dt = np.diff(times, prepend=t_last)
            d = np.diff(pos, axis=0, prepend=[[x, y, z]])
            dyaw = np.diff(yaw, prepend=yaw_last)
            # The true displacement in the body frame at the interval's mean yaw, measured...
            c, s = np.cos(yaw - 0.5 * dyaw), np.sin(yaw - 0.5 * dyaw)
            scale = om.scale_at(sim.true_odom_scales[robot], times)
            vx = scale * (c * d[:, 0] + s * d[:, 1]) / dt + om.sigma_v * od["nv"][i0:i1]
            vy = scale * (c * d[:, 1] - s * d[:, 0]) / dt + om.sigma_v * od["ny"][i0:i1]
            vz = d[:, 2] / dt + om.sigma_vz * od["nz"][i0:i1]
            w = dyaw / dt + sim.true_gyro_biases[robot] + om.sigma_w * od["nw"][i0:i1]
            # ... and integrated back at the odometry's own mean yaw.
            yaw_end = accumulate(oyaw, w * dt)
            c, s = np.cos(yaw_end - 0.5 * w * dt), np.sin(yaw_end - 0.5 * w * dt)
            xs = accumulate(ox, (c * vx - s * vy) * dt)
            ys = accumulate(oy, (s * vx + c * vy) * dt)
            zs = accumulate(oz, vz * dt)
            out.extend(
                OdometryEvent(t, robot, xi, yi, th, vi, wi, zi)
                for t, xi, yi, th, vi, wi, zi in zip(
                    times.tolist(),
                    xs.tolist(),
                    ys.tolist(),
                    wrap_angle(yaw_end).tolist(),
                    vx.tolist(),
                    w.tolist(),
                    zs.tolist(),
                    strict=True,
                )
            )
            self.odom_state[robot] = (
                float(times[-1]),
                *pos[-1].tolist(),
                float(yaw[-1]),
                float(xs[-1]),
                float(ys[-1]),
                float(zs[-1]),
                float(yaw_end[-1]),
            )

    def _height(self, t0: float, t1: float, out: list[Event]) -> None:
        sigma = self.sim.height_model.sigma if self.sim.height_model else 0.0
        for robot, (times, noise) in self.sim._heights.items():
            i0, i1 = np.searchsorted(times, [t0, t1], side="right")
            if i1 <= i0:
                continue
            z = self.sim.true_positions(robot, times[i0:i1])[:, 2] + noise[i0:i1]
            out.extend(
                HeightEvent(t, robot, zi, sigma)
                for t, zi in zip(times[i0:i1].tolist(), z.tolist(), strict=True)
            )

    def _ranges(self, t0: float, t1: float, out: list[Event]) -> None:
        sim = self.sim
        for pair in sim._uwb:
            i0, i1 = np.searchsorted(pair.t, [t0, t1], side="right")
            keep = pair.keep[i0:i1]
            if not keep.any():
                continue
            times = pair.t[i0:i1][keep]
            tm = np.maximum(times - sim.uwb_model.latency, 0.0)
            ends = []
            for robot, node in ((pair.robot_a, pair.node_a), (pair.robot_b, pair.node_b)):
                pos, yaw = sim.flights[robot].evaluate(tm)
                tag = geometry.tag_position(pos, yaw, sim.lever_arms[node])
                ends.append((tag, (pos[:, 0], pos[:, 1], yaw)))
            (tag_a, pose_a), (tag_b, pose_b) = ends
            distance = geometry.distance(tag_a, tag_b)
            if sim.range_average > 0.0:
                distance = self._averaged(pair, tm)
            rng = (
                distance
                + pair.bias
                + pair.orientation_term(pose_a, pose_b)
                + pair.noise[i0:i1][keep]
                + pair.spike[i0:i1][keep]
            )
            a, b, na, nb = pair.robot_a, pair.robot_b, pair.node_a, pair.node_b
            out.extend(
                RangeEvent(t, a, b, r, na, nb)
                for t, r in zip(times.tolist(), np.maximum(rng, 0.0).tolist(), strict=True)
            )

    def _averaged(self, pair: Any, tm: FloatArray) -> FloatArray:
        """The mean tag distance of ``pair`` over ``range_average`` seconds before each of
        ``tm`` (21 samples, none before the start)."""
        sim = self.sim
        lags = np.linspace(0.0, sim.range_average, 21)
        at = np.maximum(np.subtract.outer(tm, lags), 0.0).ravel()
        tags = []
        for robot, node in ((pair.robot_a, pair.node_a), (pair.robot_b, pair.node_b)):
            pos, yaw = sim.flights[robot].evaluate(at)
            tags.append(geometry.tag_position(pos, yaw, sim.lever_arms[node]))
        return np.asarray(geometry.distance(tags[0], tags[1])).reshape(tm.size, -1).mean(axis=1)


DRONE_PATHS: tuple[FlightPath, ...] = (
    FlightPath((-1.5, -1.0, 1.2), (2.0, 1.5, 0.2), (0.25, 0.5, 0.35), 0.05, 0.6, 0.2, yaw0=0.3),
    FlightPath((1.5, 1.5, 2.6), (1.8, 1.8, 0.25), (0.3, 0.3, 0.3), -0.08, 0.5, 0.3, yaw0=2.0),
    FlightPath((1.5, -1.5, 1.9), (2.0, 1.2, 0.25), (0.4, 0.2, 0.4), 0.0, 0.8, 0.25, yaw0=-1.2),
    FlightPath((-1.5, 1.5, 0.95), (1.5, 2.0, 0.15), (0.2, 0.3, 0.3), 0.1, 0.4, 0.15, yaw0=-2.6),
    FlightPath((0.0, 0.0, 1.55), (3.0, 2.5, 0.2), (0.15, 0.2, 0.25), -0.04, 0.7, 0.22, yaw0=0.9),
)
"""The nominal paths of ``d0``..``d4``, within +-3.5 m, 0.8-2.85 m high, at most 0.9 m/s
horizontally; the scenario draws each one's phases (and, ``heading_offsets="random"``, its
start yaw)."""

DRONE_AREA = (-4.5, 4.5, -4.5, 4.5)
"""The drones' area (xmin, xmax, ymin, ymax): their paths plus 1 m."""

DRONE_TAG_ARMS: tuple[Arm, Arm] = ((0.15, 0.0, 0.05), (-0.15, 0.0, 0.05))
"""Every drone's two tags (``n_<i>a``, ``n_<i>b``): 0.3 m apart on its x axis, 5 cm above its
centre (the same on every drone)."""


def _phased(path: FlightPath, seed: int, robot: str) -> FlightPath:
    """``path`` with ``robot``'s phases drawn from the seed (three axes and the yaw), as every
    drone scenario draws them."""
    phases = stream(seed, "flight", robot).uniform(0.0, 2.0 * math.pi, size=4)
    return replace(path, phase=tuple(phases[:3].tolist()), phase_yaw=float(phases[3]))


def drones_scenario(
    seed: int = 0,
    *,
    duration: float = 60.0,
    heading_offsets: Literal["start", "random"] = "start",
    detections: bool = False,
    uwb: UwbErrorModel = DRONE_UWB,
    odometry: FlightOdometryModel | None = None,
    height: HeightSensorModel | None = HEIGHT_SENSOR,
    odometry_topics: bool = True,
    name: str = "sim_drones",
) -> FlightSimulation:
    """Five quadrotors ``d0``..``d4`` (``d0`` the reference) on :data:`DRONE_PATHS`, two tags
    each at :data:`DRONE_TAG_ARMS`, with odometry and heights (``drones``).

    Each path's phases come from the drone's ``flight`` stream; its start yaw (the heading
    offset) is the table's (``heading_offsets="start"``) or uniform (``"random"``).
    ``detections`` is accepted for the callers of every scenario: there are no objects.
    """
    del detections
    if heading_offsets not in ("start", "random"):
        raise ValueError(f"heading_offsets must be 'start' or 'random', got {heading_offsets!r}")
    drones = []
    for i, path in enumerate(DRONE_PATHS):
        robot = f"d{i}"
        flown = _phased(path, seed, robot)
        if heading_offsets == "random":
            yaw0 = float(stream(seed, "initial-yaw", robot).uniform(-math.pi, math.pi))
            flown = replace(flown, yaw0=yaw0)
        tags = ((f"n_{i}a", DRONE_TAG_ARMS[0]), (f"n_{i}b", DRONE_TAG_ARMS[1]))
        drones.append(Drone(robot, flown, tags))
    return FlightSimulation(
        drones,
        reference="d0",
        seed=seed,
        duration=duration,
        name=name,
        area=DRONE_AREA,
        uwb=uwb,
        odometry=odometry,
        height=height,
        odometry_topics=odometry_topics,
    )


def drones_uwb_scenario(seed: int = 0, **options: Any) -> FlightSimulation:
    """:func:`drones_scenario`, the same flight, with UWB only: no odometry, no heights."""
    return drones_scenario(
        seed, odometry_topics=False, height=None, name="sim_drones_uwb", **options
    )


SIX_TAG_ARMS: tuple[Arm, ...] = (
    (0.2, 0.0, 0.05),
    (-0.2, 0.0, 0.05),
    (0.0, 0.2, 0.05),
    (0.0, -0.2, 0.05),
    (0.12, 0.12, -0.08),
    (-0.12, -0.12, -0.08),
)
"""The six tags of a ``drones_six`` quadrotor (``n_<i>a``..``n_<i>f``): four at the ends of
its 0.4 m cross, 5 cm above its centre, two on a diagonal 8 cm below: not coplanar, so the
tags alone tell a drone's yaw and the formation from its mirror image."""

SIX_TAG_UWB = replace(DRONE_UWB, sigma=0.03, rate_hz=1.0, nlos_probability=0.0, jitter=0.0)
"""``drones_six``'s UWB: every tag pair at 1 Hz at its own random phase, 3 cm of white noise,
no NLOS spikes (the ranges are averaged: :data:`SIX_TAG_AVERAGE`)."""

SIX_TAG_AVERAGE = 1.0
"""Seconds each ``drones_six`` range averages the distance over, up to its stamp."""


def drones_six_scenario(
    seed: int = 0,
    *,
    duration: float = 120.0,
    uwb: UwbErrorModel = SIX_TAG_UWB,
    detections: bool = False,
    name: str = "sim_drones_six",
) -> FlightSimulation:
    """Three quadrotors ``d0``..``d2`` (``d0`` the reference) on the first three
    :data:`DRONE_PATHS`, six tags each at :data:`SIX_TAG_ARMS`, ranges averaged over
    :data:`SIX_TAG_AVERAGE` at 1 Hz per pair, no odometry, no heights (``drones_six``): a
    simulated stand-in for a LinkTrack team under motion capture. The paths' phases are drawn
    as :func:`drones_scenario` draws them."""
    del detections
    drones = []
    for i, path in enumerate(DRONE_PATHS[:3]):
        robot = f"d{i}"
        flown = _phased(path, seed, robot)
        tags = tuple((f"n_{i}{'abcdef'[k]}", arm) for k, arm in enumerate(SIX_TAG_ARMS))
        drones.append(Drone(robot, flown, tags))
    return FlightSimulation(
        drones,
        reference="d0",
        seed=seed,
        duration=duration,
        name=name,
        area=DRONE_AREA,
        uwb=uwb,
        height=None,
        odometry_topics=False,
        range_average=SIX_TAG_AVERAGE,
    )
