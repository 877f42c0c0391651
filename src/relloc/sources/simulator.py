"""A simulated robot team as an event source.

What it is
----------
A small, deterministic 2D world in which differential-drive robots move (on the paper's
patterns, or under velocity commands for closed-loop navigation) and their sensors produce
exactly the events a real recording or a live team produces (:mod:`relloc.events`):

* odometry at 20 Hz per robot, in the robot's *own* odometry frame (the frame is the robot's
  pose at ``t = 0``), integrated from a noisy twist: a per-robot wheel-scale error, velocity
  noise and a small gyro bias make it drift like real wheel odometry (about 1 % of the path);
* UWB ranges for every pair of transceivers (:class:`UwbErrorModel`): a per-pair bias, an
  error that depends smoothly on each end's heading relative to the bearing to the other end
  (antenna pattern and body occlusion), Gaussian noise, positive NLOS spikes and dropouts, each
  pair at its own rate with its own phase and jitter;
* detections of static objects by each robot's forward camera at about 5 Hz
  (:class:`DetectionErrorModel`), in the robot body frame, with depth noise growing with
  distance and occasional misses;
* ground truth (the "motion capture") at 20 Hz in the world frame.

Why it is built this way
------------------------
* **Deterministic and stable under change.** Every random quantity comes from its own
  sub-stream of ``numpy.random.default_rng``, keyed by the seed, what it is and whose it is
  (e.g. the noise of the UWB pair ``n_1-n_3``). Switching detections on, adding a robot or
  lengthening the run therefore does not change the UWB noise of an existing pair. All sensor
  time stamps and noise draws are fixed when the simulation is built, so the step-wise API
  (:meth:`Simulation.advance`) returns the same events however the run is cut into steps.
* **Exact kinematics.** Motion is a sequence of constant-twist segments (straight lines, turns
  in place, circular arcs), integrated in closed form; ground truth has no integration error,
  and the odometry error is exactly the error model's, nothing else.
* **Truthful configuration.** :attr:`Simulation.config` is the team configuration a user would
  write for this team: UWB node ids, the true per-pair biases and the true heading offset of
  each odometry frame (the "compass" the paper assumes). What a real team would *not* know
  (wheel scales, gyro biases, the orientation-dependent range error) stays in the simulation,
  exposed as attributes for tests and calibration experiments.

Scenarios
---------
:func:`multi_scenario` is the paper's five-robot experiment in the 8 m x 9 m arena (a static
reference robot and four robots on a triangle, an X, a circle and a rectangle),
:func:`single_scenario` the two-robot single-range experiment, and :func:`nav_scenario` the
multi team with one robot driven by velocity commands.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from itertools import combinations
from operator import attrgetter
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from relloc.config import (
    CameraConfig,
    FilterConfig,
    PairCalibration,
    RobotConfig,
    TeamConfig,
    UwbConfig,
)
from relloc.events import (
    DetectionEvent,
    Event,
    GroundTruthEvent,
    ObjectDetection,
    OdometryEvent,
    RangeEvent,
    pair_key,
)
from relloc.odometry import wrap_angle

__all__ = [
    "ARENA",
    "ActuationModel",
    "DetectionErrorModel",
    "OdometryErrorModel",
    "RobotMotion",
    "SimObject",
    "Simulation",
    "UwbErrorModel",
    "covisibility",
    "multi_scenario",
    "nav_scenario",
    "single_scenario",
]

FloatArray = NDArray[np.float64]

ARENA: tuple[float, float, float, float] = (-4.0, 4.0, -4.5, 4.5)
"""The TIERS arena (xmin, xmax, ymin, ymax), about 8 m x 9 m."""

TWO_PI = 2.0 * math.pi
SIM_PARTICLES = 20000
"""Particle count of the simulated teams' filter (see ``Simulation.config``)."""


# ============================================================================ error models
@dataclass(frozen=True)
class UwbErrorModel:
    """How a UWB range differs from the true distance between two transceivers.

    ``range = distance + bias_pair + orientation_term + N(0, sigma^2) + NLOS spike``, and a
    fraction ``dropout_probability`` of the ranges never arrives. The orientation term is
    ``A_a g(alpha_a - phi_a) + A_b g(alpha_b - phi_b)`` where ``alpha`` is an end's heading
    relative to the bearing to the other end, ``phi`` a per-node antenna offset, ``A`` a
    per-pair, per-end amplitude and ``g(a) = -cos(a) + 0.3 cos(2a)``: zero on average over
    headings (so ``bias_pair`` is the pair's bias), largest when the other robot is behind (the
    signal crosses the body). Over one run the headings are not uniform, so a pair's median
    error can differ from its bias by a few centimetres (up to about 0.08 m at the default
    amplitude, most for pairs with the static robot): what a learned correction can remove.
    """

    bias_range: tuple[float, float] = (0.1, 0.5)
    """Per-pair bias drawn uniformly in this interval (m)."""
    orientation_amplitude: float = 0.05
    """Typical amplitude of the heading-dependent error at each end (m); each pair draws its
    own in [0.5, 1.5] times this."""
    sigma: float = 0.05
    """Standard deviation of the white range noise (m)."""
    nlos_probability: float = 0.03
    """Probability that a range is an NLOS spike."""
    nlos_range: tuple[float, float] = (0.3, 1.5)
    """An NLOS spike adds a positive error drawn uniformly in this interval (m)."""
    dropout_probability: float = 0.05
    """Probability that a range is lost."""
    rate_hz: float = 10.0
    """Ranging rate of each pair; every pair has its own random phase."""
    jitter: float = 0.003
    """Standard deviation of the time-stamp jitter (s), clipped to a quarter period."""
    latency: float = 0.0
    """The range is measured this long before its stamp (s); real DWM1001 ranges lag."""


@dataclass(frozen=True)
class OdometryErrorModel:
    """Wheel/gyro odometry errors, per robot and per sample.

    The measured twist over each odometry interval is
    ``v_m = scale * v + N(0, sigma_v^2)`` and ``w_m = w + gyro_bias + N(0, sigma_w^2)``; the
    noise and the bias only apply while the robot moves (a wheel-encoder odometry at rest
    reports no motion).
    """

    scale_range: tuple[float, float] = (0.97, 1.03)
    """Per-robot wheel-scale factor drawn uniformly in this interval."""
    sigma_v: float = 0.01
    """Forward-speed noise per sample (m/s)."""
    sigma_w: float = 0.015
    """Yaw-rate noise per sample (rad/s)."""
    gyro_bias_max: float = 0.0015
    """Per-robot constant yaw-rate bias, drawn uniformly in +-this (rad/s; 0.0015 rad/s is
    5 degrees a minute)."""
    rate_hz: float = 20.0


@dataclass(frozen=True)
class DetectionErrorModel:
    """Object detections of a forward camera (field of view and range from the team config).

    The detected position is the true one seen from the camera with the distance perturbed by
    ``N(0, (depth_sigma_0 + depth_sigma_per_m * d)^2)`` (stereo depth) and the bearing by
    ``N(0, bearing_sigma^2)``; a visible object is missed with ``miss_probability``.
    Occlusions and false positives are not simulated; the visibility test is in the ground
    plane (camera pitch is ignored).
    """

    rate_hz: float = 5.0
    depth_sigma_0: float = 0.02
    depth_sigma_per_m: float = 0.02
    bearing_sigma: float = 0.01
    """Bearing noise (rad)."""
    height_sigma: float = 0.02
    miss_probability: float = 0.1
    min_range: float = 0.3
    """Objects closer than this are not detected (m)."""


@dataclass(frozen=True)
class ActuationModel:
    """How a commanded robot executes a velocity command ``(v, w)``.

    Commands are clipped to the limits; the executed twist is
    ``v * (1 + N(0, rel_sigma^2))`` and ``w * (1 + N(0, rel_sigma^2)) + N(0, sigma_w^2)``
    (the latter only while moving), redrawn at every simulation step.
    """

    max_v: float = 0.5
    max_w: float = 2.0
    rel_sigma: float = 0.05
    sigma_w: float = 0.02
    dt: float = 0.01
    """Simulation step of commanded robots (s); a command takes effect at the next step."""


# ============================================================================ world
@dataclass(frozen=True)
class SimObject:
    """A static object in the world."""

    label: str
    x: float
    y: float
    z: float = 0.5
    """Height of the object's centre above the floor (m)."""


@dataclass(frozen=True)
class RobotMotion:
    """How one simulated robot moves.

    The robot starts at ``(x, y, yaw)`` (world frame) and executes ``segments``, a sequence
    of ``(duration, v, w)`` constant-twist pieces, then stands still; a ``commanded`` robot
    ignores ``segments`` and executes :meth:`Simulation.set_command` instead.
    """

    name: str
    node: str
    x: float
    y: float
    yaw: float
    segments: tuple[tuple[float, float, float], ...] = ()
    commanded: bool = False
    pattern: str = ""
    """Name of the pattern, for display only."""


class _Trajectory:
    """Piecewise constant-twist motion of a unicycle, integrated in closed form.

    Segment ``k`` starts at ``t0[k]`` in state ``(x, y, yaw, s)`` (yaw unwrapped, ``s`` the
    signed path length) and moves with ``(v[k], w[k])``; the last entry is the end state, at
    rest forever after. Evaluation is vectorised over time.
    """

    def __init__(self, x: float, y: float, yaw: float) -> None:
        self._t0 = np.zeros(1)
        self._state = np.array([[x, y, yaw, 0.0]])
        self._v = np.zeros(1)
        self._w = np.zeros(1)

    @property
    def end_time(self) -> float:
        return float(self._t0[-1])

    def copy(self) -> _Trajectory:
        new = _Trajectory.__new__(_Trajectory)
        new._t0, new._state, new._v, new._w = self._t0, self._state, self._v, self._w
        return new  # arrays are never modified in place, so sharing them is safe

    def extend(self, durations: ArrayLike, v: ArrayLike, w: ArrayLike) -> None:
        """Append segments after the current end."""
        d = np.asarray(durations, dtype=float)
        if d.size == 0:
            return
        v = np.broadcast_to(np.asarray(v, dtype=float), d.shape)
        w = np.broadcast_to(np.asarray(w, dtype=float), d.shape)
        x, y, yaw, s = self._state[-1]
        yaw_end = _accumulate(yaw, w * d)
        yaw_start = yaw_end - w * d
        dx, dy = _arc_displacement(yaw_start, v, w, d)
        states = np.column_stack(
            [_accumulate(x, dx), _accumulate(y, dy), yaw_end, _accumulate(s, v * d)]
        )
        self._t0 = np.concatenate([self._t0, self._t0[-1] + np.cumsum(d)])
        self._state = np.concatenate([self._state, states])
        self._v = np.concatenate([self._v[:-1], v, [0.0]])
        self._w = np.concatenate([self._w[:-1], w, [0.0]])

    def evaluate(self, t: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """``x, y, yaw (unwrapped), s`` at times ``t`` (before 0: the start; after the end: the
        end state)."""
        t = np.asarray(t, dtype=float)
        k = np.clip(np.searchsorted(self._t0, t, side="right") - 1, 0, None)
        tau = np.maximum(t - self._t0[k], 0.0)
        x0, y0, yaw0, s0 = self._state[k].T
        v, w = self._v[k], self._w[k]
        dx, dy = _arc_displacement(yaw0, v, w, tau)
        return x0 + dx, y0 + dy, yaw0 + w * tau, s0 + v * tau


def _arc_displacement(
    yaw: FloatArray, v: FloatArray, w: FloatArray, dt: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """World displacement of a unicycle moving with constant ``(v, w)`` for ``dt`` from ``yaw``.

    The chord of the arc, ``v dt sin(w dt / 2) / (w dt / 2)``, along the mean heading: exact
    for any ``w`` including 0 (``np.sinc`` handles the limit).
    """
    chord = v * dt * np.sinc(w * dt / TWO_PI)
    mid = yaw + 0.5 * w * dt
    return chord * np.cos(mid), chord * np.sin(mid)


def _accumulate(start: float, steps: FloatArray) -> FloatArray:
    """``start + steps[0]``, ``start + steps[0] + steps[1]``, ... summed strictly in order.

    Unlike ``start + np.cumsum(steps)``, continuing from the last value later gives bit-for-bit
    the same numbers as one long sum, so a run cut into steps equals the run in one go.
    """
    return np.cumsum(np.concatenate(([start], steps)))[1:]


def _stream(seed: int, *names: str) -> np.random.Generator:
    """An independent random stream for ``names`` (e.g. ``("uwb-noise", "n_1-n_3")``)."""
    key = tuple(zlib.crc32(n.encode()) for n in names)
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=key))


# ============================================================================ simulation
class Simulation:
    """A simulated team: ground-truth motion, sensors, and the team config for the filter.

    Use :meth:`events` for an open-loop run (the whole run, time-ordered), or
    :meth:`advance` with :meth:`set_command` for closed-loop control of the ``commanded``
    robots. The two are independent: :meth:`events` always replays the run from the start
    (commanded robots then stand still) and does not touch the closed-loop state.

    Attributes
    ----------
    config
        The team configuration the localizer should use (truthful node ids, per-pair biases
        and heading offsets; ``odom_scale`` is left at 1 as a real team would not know it).
    true_biases
        Per-pair UWB bias by node pair key (``"n_0-n_1"``).
    true_heading_offsets
        Rotation of each robot's odometry frame into the world frame (rad): its yaw at t = 0.
    true_odom_scales, true_gyro_biases
        Per-robot odometry errors (wheel-scale factor; yaw-rate bias in rad/s).
    objects
        ``(label, x, y)`` of the static objects (empty unless detections are simulated).
    duration
        Length of the run (s); no event is stamped later.
    """

    def __init__(
        self,
        robots: Sequence[RobotMotion],
        *,
        reference: str,
        seed: int = 0,
        duration: float = 60.0,
        name: str = "sim",
        objects: Sequence[SimObject] = (),
        detections: bool = False,
        uwb: UwbErrorModel | None = None,
        odometry: OdometryErrorModel | None = None,
        camera: DetectionErrorModel | None = None,
        actuation: ActuationModel | None = None,
        camera_config: CameraConfig | None = None,
        area: tuple[float, float, float, float] = ARENA,
    ) -> None:
        if duration <= 0:
            raise ValueError(f"duration must be positive, got {duration}")
        self.seed = int(seed)
        self.duration = float(duration)
        self.motions: tuple[RobotMotion, ...] = tuple(robots)
        self.robots: tuple[str, ...] = tuple(m.name for m in self.motions)
        self.commanded: tuple[str, ...] = tuple(m.name for m in self.motions if m.commanded)
        self.reference = reference
        self.uwb_model = uwb or UwbErrorModel()
        self.odometry_model = odometry or OdometryErrorModel()
        self.detection_model = camera or DetectionErrorModel()
        self.actuation_model = actuation or ActuationModel()
        self.detections_enabled = bool(detections)
        self.camera = camera_config or CameraConfig(x=0.1, z=0.25, fov_deg=70.0, max_range=5.0)
        self.sim_objects: tuple[SimObject, ...] = tuple(objects) if detections else ()
        self.objects: list[tuple[str, float, float]] = [
            (o.label, o.x, o.y) for o in self.sim_objects
        ]
        self._obj_xyz = np.array([[o.x, o.y, o.z] for o in self.sim_objects]).reshape(-1, 3)

        # Pattern trajectories (shared, immutable) and commanded start poses.
        self._base_traj: dict[str, _Trajectory] = {}
        for m in self.motions:
            traj = _Trajectory(m.x, m.y, m.yaw)
            if not m.commanded and m.segments:
                d, v, w = np.asarray(m.segments, dtype=float).T
                traj.extend(d, v, w)
            self._base_traj[m.name] = traj
        self.true_heading_offsets: dict[str, float] = {
            m.name: float(wrap_angle(m.yaw)) for m in self.motions
        }

        self._build_odometry()
        self._build_uwb()
        self._build_camera()
        self._build_actuation()
        self._gt_times = np.arange(0.0, self.duration + 1e-9, 0.05)

        robot_cfgs = tuple(
            RobotConfig(
                name=m.name,
                uwb_node=m.node,
                odom_mode="pose",
                heading_offset_deg=math.degrees(self.true_heading_offsets[m.name]),
                camera=self.camera,
            )
            for m in self.motions
        )
        self.config = TeamConfig(
            robots=robot_cfgs,
            reference=reference,
            name=name,
            area=area,
            uwb=UwbConfig(
                pairs={
                    k: PairCalibration(bias=b, source="simulator")
                    for k, b in self.true_biases.items()
                }
            ),
            # Every robot but the reference moves in the simulated scenarios, so the rotation
            # ambiguity of the uniform start resolves within a second: 20 000 particles do as
            # well as the 50 000 the mostly static TIERS shortbag needs (seeds 0-3 agree within
            # the seed-to-seed spread), at less than half the cost.
            filter=FilterConfig(particles=SIM_PARTICLES),
        )
        self._runner = _Runner(self)

    # ------------------------------------------------------------------ construction
    def _build_odometry(self) -> None:
        om = self.odometry_model
        self.true_odom_scales: dict[str, float] = {}
        self.true_gyro_biases: dict[str, float] = {}
        self._odom: dict[str, dict[str, FloatArray]] = {}
        period = 1.0 / om.rate_hz
        for m in self.motions:
            rng = _stream(self.seed, "odom-params", m.name)
            self.true_odom_scales[m.name] = float(rng.uniform(*om.scale_range))
            self.true_gyro_biases[m.name] = float(rng.uniform(-om.gyro_bias_max, om.gyro_bias_max))
            phase = rng.uniform(0.0, period)
            times = np.arange(phase, self.duration + 1e-9, period)
            self._odom[m.name] = {
                "t": times,
                "nv": _stream(self.seed, "odom-v", m.name).standard_normal(times.size),
                "nw": _stream(self.seed, "odom-w", m.name).standard_normal(times.size),
            }

    def _build_uwb(self) -> None:
        um = self.uwb_model
        period = 1.0 / um.rate_hz
        nodes = [m.node for m in self.motions]
        antenna = {n: float(_stream(self.seed, "uwb-antenna", n).uniform(-0.5, 0.5)) for n in nodes}
        self.true_biases: dict[str, float] = {}
        self._uwb: list[_UwbPair] = []
        for ma, mb in combinations(self.motions, 2):
            key = pair_key(ma.node, mb.node)
            bias = float(_stream(self.seed, "uwb-bias", key).uniform(*um.bias_range))
            self.true_biases[key] = bias
            amp = _stream(self.seed, "uwb-orient", key).uniform(0.5, 1.5, size=2)
            rng_t = _stream(self.seed, "uwb-time", key)
            phase = rng_t.uniform(0.0, period)
            base = np.arange(phase, self.duration + period, period)
            jitter = np.clip(rng_t.normal(0.0, um.jitter, base.size), -period / 4, period / 4)
            times = base + jitter
            n = times.size
            spikes = _stream(self.seed, "uwb-nlos", key).uniform(0.0, 1.0, size=(n, 2))
            nlos = spikes[:, 0] < um.nlos_probability
            lo, hi = um.nlos_range
            mask = (times >= 0.0) & (times <= self.duration)
            self._uwb.append(
                _UwbPair(
                    robot_a=ma.name,
                    robot_b=mb.name,
                    node_a=ma.node,
                    node_b=mb.node,
                    bias=bias,
                    amplitude=amp * um.orientation_amplitude,
                    antenna=np.array([antenna[ma.node], antenna[mb.node]]),
                    t=times[mask],
                    noise=(_stream(self.seed, "uwb-noise", key).standard_normal(n) * um.sigma)[
                        mask
                    ],
                    spike=np.where(nlos, lo + spikes[:, 1] * (hi - lo), 0.0)[mask],
                    keep=(
                        _stream(self.seed, "uwb-dropout", key).uniform(size=n)
                        >= um.dropout_probability
                    )[mask],
                )
            )

    def _build_camera(self) -> None:
        dm = self.detection_model
        self._cam: dict[str, dict[str, FloatArray]] = {}
        if not self.detections_enabled:
            return
        period = 1.0 / dm.rate_hz
        n_obj = len(self.sim_objects)
        for m in self.motions:
            rng_t = _stream(self.seed, "camera-time", m.name)
            phase = rng_t.uniform(0.0, period)
            times = np.arange(phase, self.duration + 1e-9, period)
            rng = _stream(self.seed, "camera-noise", m.name)
            shape = (times.size, n_obj)
            self._cam[m.name] = {
                "t": times,
                "miss": rng.uniform(size=shape) < dm.miss_probability,
                "nd": rng.standard_normal(shape),
                "nb": rng.standard_normal(shape),
                "nz": rng.standard_normal(shape),
                "score": rng.uniform(0.5, 0.95, size=shape),
            }

    def _build_actuation(self) -> None:
        am = self.actuation_model
        n = math.ceil(self.duration / am.dt) + 2
        self._act: dict[str, FloatArray] = {
            name: _stream(self.seed, "actuation", name).standard_normal((n, 3))
            for name in self.commanded
        }

    # ------------------------------------------------------------------ public API
    def events(self) -> Iterator[Event]:
        """All events of the run, time-ordered, from a fresh start (open loop).

        Generated in chunks of a few seconds, so a long run does not sit in memory at once.
        Commanded robots stand still (they get no commands).
        """
        runner = _Runner(self)
        t = 0.0
        while True:
            t = min(t + 5.0, self.duration)
            yield from runner.advance(t)
            if t >= self.duration:
                return

    def advance(self, t_until: float) -> list[Event]:
        """Simulate up to ``t_until`` (capped at :attr:`duration`) and return the new events.

        Events are time-ordered and stamped in ``(t_previous, t_until]`` (the first call also
        includes ``t = 0``). Commanded robots execute the command set last, from the end of the
        previous step.
        """
        return self._runner.advance(t_until)

    @property
    def time(self) -> float:
        """Time up to which the closed-loop run has been simulated (s)."""
        return max(self._runner.t_done, 0.0)

    def set_command(self, robot: str, v: float, w: float) -> None:
        """Velocity command ``(v, w)`` (m/s, rad/s) for a commanded robot, held until changed."""
        if robot not in self.commanded:
            raise ValueError(f"{robot!r} is not a commanded robot; those are {self.commanded}")
        self._runner.commands[robot] = (float(v), float(w))

    def true_pose(self, robot: str, t: float) -> tuple[float, float, float]:
        """True world pose ``(x, y, yaw)`` of ``robot`` at time ``t`` (yaw in [-pi, pi))."""
        x, y, yaw = self.true_poses(robot, np.array([t]))[0]
        return float(x), float(y), float(yaw)

    def true_poses(self, robot: str, t: ArrayLike) -> FloatArray:
        """True world poses at times ``t``: array ``(n, 3)`` of ``x, y, yaw``.

        For a commanded robot only the closed-loop run simulated so far is known.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if robot not in self._base_traj:
            raise KeyError(f"unknown robot {robot!r}; the team is {list(self.robots)}")
        if robot in self.commanded and t.size and t.max() > self._runner.t_sim + 1e-9:
            raise ValueError(
                f"{robot!r} is commanded and simulated only up to t={self._runner.t_sim:.3f}s"
            )
        x, y, yaw, _ = self._runner.traj[robot].evaluate(t)
        return np.column_stack([x, y, wrap_angle(yaw)])

    def range_error(self, robot_a: str, robot_b: str, t: ArrayLike) -> FloatArray:
        """Deterministic part of the UWB error (bias + orientation term) at times ``t``.

        What a perfect range-correction model would predict; the rest is white noise and NLOS.
        """
        for pair in self._uwb:
            if {pair.robot_a, pair.robot_b} == {robot_a, robot_b}:
                t = np.atleast_1d(np.asarray(t, dtype=float))
                pa = self._runner.traj[pair.robot_a].evaluate(t)
                pb = self._runner.traj[pair.robot_b].evaluate(t)
                return pair.bias + pair.orientation_term(pa, pb)
        raise KeyError(f"no UWB pair {robot_a!r}-{robot_b!r}")


@dataclass(frozen=True, eq=False)
class _UwbPair:
    """One transceiver pair: its error parameters and its pre-drawn schedule and noise.

    ``t`` are the stamps of all scheduled ranges; ``noise``, ``spike`` (NLOS error, 0 when
    none) and ``keep`` (False: dropped) are aligned with them.
    """

    robot_a: str
    robot_b: str
    node_a: str
    node_b: str
    bias: float
    amplitude: FloatArray
    """Orientation-error amplitude at end a and end b (m)."""
    antenna: FloatArray
    """Antenna-pattern offset of node a and node b (rad)."""
    t: FloatArray
    noise: FloatArray
    spike: FloatArray
    keep: NDArray[np.bool_]

    def orientation_term(
        self, pa: tuple[FloatArray, ...], pb: tuple[FloatArray, ...]
    ) -> FloatArray:
        """Heading-dependent range error for poses ``pa``, ``pb`` (see :class:`UwbErrorModel`)."""
        bearing_ab = np.arctan2(pb[1] - pa[1], pb[0] - pa[0])
        alpha_a = pa[2] - bearing_ab - self.antenna[0]
        alpha_b = pb[2] - (bearing_ab + math.pi) - self.antenna[1]
        gain_a, gain_b = _antenna_gain(alpha_a), _antenna_gain(alpha_b)
        return self.amplitude[0] * gain_a + self.amplitude[1] * gain_b


def _antenna_gain(alpha: FloatArray) -> FloatArray:
    """Shape of the heading-dependent error: +1.3 with the other end behind, zero mean."""
    return -np.cos(alpha) + 0.3 * np.cos(2.0 * alpha)


class _Runner:
    """Mutable state of one run: how far it got, odometry integrators, commanded robots."""

    def __init__(self, sim: Simulation) -> None:
        self.sim = sim
        self.t_done = -1.0
        self.t_sim = 0.0  # commanded robots are integrated up to here
        self.traj = {name: tr.copy() for name, tr in sim._base_traj.items()}
        self.commands: dict[str, tuple[float, float]] = {name: (0.0, 0.0) for name in sim.commanded}
        # Per robot: last odometry time, true (s, unwrapped yaw) then, and the odometry pose
        # (x, y, unwrapped yaw) then. The odometry frame is the pose at t = 0.
        self.odom_state: dict[str, tuple[float, ...]] = {}
        for name in sim.robots:
            _, _, yaw, s = self.traj[name].evaluate(np.array([0.0]))
            self.odom_state[name] = (0.0, float(s[0]), float(yaw[0]), 0.0, 0.0, 0.0)

    def advance(self, t_until: float) -> list[Event]:
        t_until = min(float(t_until), self.sim.duration)
        if t_until <= self.t_done:
            return []
        self._step_commanded(t_until)
        t0 = self.t_done
        out: list[Event] = []
        self._ground_truth(t0, t_until, out)
        self._odometry(t0, t_until, out)
        self._ranges(t0, t_until, out)
        self._detections(t0, t_until, out)
        out.sort(key=attrgetter("t"))
        self.t_done = t_until
        return out

    # -------------------------------------------------------------- dynamics
    def _step_commanded(self, t_until: float) -> None:
        am = self.sim.actuation_model
        if not self.sim.commanded:
            self.t_sim = max(self.t_sim, t_until)
            return
        k0 = round(self.t_sim / am.dt)
        n = max(math.ceil(t_until / am.dt - 1e-9) - k0, 0)
        if n == 0:
            return
        for name in self.sim.commanded:
            v_cmd, w_cmd = self.commands[name]
            v_cmd = float(np.clip(v_cmd, -am.max_v, am.max_v))
            w_cmd = float(np.clip(w_cmd, -am.max_w, am.max_w))
            noise = self.sim._act[name][k0 : k0 + n]
            moving = 1.0 if (v_cmd != 0.0 or w_cmd != 0.0) else 0.0
            v = v_cmd * (1.0 + am.rel_sigma * noise[:, 0])
            w = w_cmd * (1.0 + am.rel_sigma * noise[:, 1]) + moving * am.sigma_w * noise[:, 2]
            self.traj[name].extend(np.full(n, am.dt), v, w)
        self.t_sim = (k0 + n) * am.dt

    # -------------------------------------------------------------- sensors
    def _ground_truth(self, t0: float, t1: float, out: list[Event]) -> None:
        times = _window(self.sim._gt_times, t0, t1)
        if times.size == 0:
            return
        for name in self.sim.robots:
            x, y, yaw, _ = self.traj[name].evaluate(times)
            yaw = wrap_angle(yaw)
            out.extend(
                GroundTruthEvent(t, name, xi, yi, th)
                for t, xi, yi, th in zip(
                    times.tolist(), x.tolist(), y.tolist(), yaw.tolist(), strict=True
                )
            )

    def _odometry(self, t0: float, t1: float, out: list[Event]) -> None:
        om = self.sim.odometry_model
        for name in self.sim.robots:
            od = self.sim._odom[name]
            i0, i1 = np.searchsorted(od["t"], [t0, t1], side="right")
            if i1 <= i0:
                continue
            times = od["t"][i0:i1]
            t_last, s_last, yaw_last, ox, oy, oyaw = self.odom_state[name]
            _, _, yaw, s = self.traj[name].evaluate(times)
            dt = np.diff(times, prepend=t_last)
            ds = np.diff(s, prepend=s_last)
            dyaw = np.diff(yaw, prepend=yaw_last)
            moving = (np.abs(ds) > 1e-12) | (np.abs(dyaw) > 1e-12)
            v_m = self.sim.true_odom_scales[name] * ds / dt + moving * om.sigma_v * od["nv"][i0:i1]
            w_m = dyaw / dt + moving * (
                self.sim.true_gyro_biases[name] + om.sigma_w * od["nw"][i0:i1]
            )
            yaw_end = _accumulate(oyaw, w_m * dt)
            dx, dy = _arc_displacement(yaw_end - w_m * dt, v_m, w_m, dt)
            xs, ys = _accumulate(ox, dx), _accumulate(oy, dy)
            out.extend(
                OdometryEvent(t, name, xi, yi, th, vi, wi)
                for t, xi, yi, th, vi, wi in zip(
                    times.tolist(),
                    xs.tolist(),
                    ys.tolist(),
                    wrap_angle(yaw_end).tolist(),
                    v_m.tolist(),
                    w_m.tolist(),
                    strict=True,
                )
            )
            self.odom_state[name] = (
                float(times[-1]),
                float(s[-1]),
                float(yaw[-1]),
                float(xs[-1]),
                float(ys[-1]),
                float(yaw_end[-1]),
            )

    def _ranges(self, t0: float, t1: float, out: list[Event]) -> None:
        latency = self.sim.uwb_model.latency
        for pair in self.sim._uwb:
            i0, i1 = np.searchsorted(pair.t, [t0, t1], side="right")
            keep = pair.keep[i0:i1]
            if not keep.any():
                continue
            times = pair.t[i0:i1][keep]
            tm = np.maximum(times - latency, 0.0)
            pa = self.traj[pair.robot_a].evaluate(tm)
            pb = self.traj[pair.robot_b].evaluate(tm)
            dist = np.hypot(pb[0] - pa[0], pb[1] - pa[1])
            rng = (
                dist
                + pair.bias
                + pair.orientation_term(pa, pb)
                + pair.noise[i0:i1][keep]
                + pair.spike[i0:i1][keep]
            )
            rng = np.maximum(rng, 0.0)
            a, b, na, nb = pair.robot_a, pair.robot_b, pair.node_a, pair.node_b
            out.extend(
                RangeEvent(t, a, b, r, na, nb)
                for t, r in zip(times.tolist(), rng.tolist(), strict=True)
            )

    def _detections(self, t0: float, t1: float, out: list[Event]) -> None:
        sim = self.sim
        if not sim.detections_enabled:
            return
        dm, cam = sim.detection_model, sim.camera
        labels = [o.label for o in sim.sim_objects]
        for name in sim.robots:
            cd = sim._cam[name]
            i0, i1 = np.searchsorted(cd["t"], [t0, t1], side="right")
            if i1 <= i0:
                continue
            times = cd["t"][i0:i1]
            x, y, yaw, _ = self.traj[name].evaluate(times)
            d, bearing = _camera_view(x, y, yaw, cam, sim._obj_xyz)
            visible = _in_view(d, bearing, cam, dm.min_range) & ~cd["miss"][i0:i1]
            d_m = d + (dm.depth_sigma_0 + dm.depth_sigma_per_m * d) * cd["nd"][i0:i1]
            b_m = bearing + dm.bearing_sigma * cd["nb"][i0:i1]
            # Camera-level frame -> body frame (camera yaw, then its offset on the robot).
            cyaw = math.radians(cam.yaw_deg)
            bx = cam.x + d_m * np.cos(b_m + cyaw)
            by = cam.y + d_m * np.sin(b_m + cyaw)
            bz = sim._obj_xyz[:, 2] + dm.height_sigma * cd["nz"][i0:i1]
            score = cd["score"][i0:i1]
            for f, t in enumerate(times.tolist()):
                objs = tuple(
                    ObjectDetection(
                        labels[j],
                        float(bx[f, j]),
                        float(by[f, j]),
                        float(bz[f, j]),
                        float(score[f, j]),
                    )
                    for j in np.flatnonzero(visible[f])
                )
                out.append(DetectionEvent(t, name, objs))


def _window(times: FloatArray, t0: float, t1: float) -> FloatArray:
    """The sorted ``times`` in ``(t0, t1]``."""
    i0, i1 = np.searchsorted(times, [t0, t1], side="right")
    return times[i0:i1]


def _camera_view(
    x: FloatArray, y: FloatArray, yaw: FloatArray, cam: CameraConfig, obj_xyz: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Distance and bearing (relative to the camera axis) of every object from every pose.

    Arrays of shape ``(n_poses, n_objects)``; distances are horizontal, from the camera.
    """
    c, s = np.cos(yaw), np.sin(yaw)
    cx = x + c * cam.x - s * cam.y
    cy = y + s * cam.x + c * cam.y
    rx = obj_xyz[None, :, 0] - cx[:, None]
    ry = obj_xyz[None, :, 1] - cy[:, None]
    d = np.hypot(rx, ry)
    bearing = wrap_angle(np.arctan2(ry, rx) - (yaw + math.radians(cam.yaw_deg))[:, None])
    return d, bearing


def _in_view(d: FloatArray, bearing: FloatArray, cam: CameraConfig, min_range: float) -> NDArray:
    """Whether objects at ``(d, bearing)`` from the camera are in its field of view and range."""
    half_fov = 0.5 * math.radians(cam.fov_deg)
    return (d <= cam.max_range) & (d >= min_range) & (np.abs(bearing) <= half_fov)


def covisibility(sim: Simulation, dt: float = 0.2) -> dict[str, float]:
    """How often pairs of robots see a common object at the same time (ideal cameras).

    Checked on a grid of period ``dt`` with the true poses (no misses, no noise). Returns the
    fraction of time for each robot pair (key ``pair_key(a, b)``), plus ``"any"``: the
    fraction of time at least one pair co-sees an object, and ``"mean_pairs"``: the mean
    number of co-seeing pairs. For a commanded robot only the closed-loop run so far counts.
    """
    if not sim.sim_objects:
        return {"any": 0.0, "mean_pairs": 0.0}
    t_end = sim._runner.t_sim if sim.commanded else sim.duration
    times = np.arange(0.0, t_end + 1e-9, dt)
    seen = {}
    for name in sim.robots:
        x, y, yaw, _ = sim._runner.traj[name].evaluate(times)
        d, bearing = _camera_view(x, y, yaw, sim.camera, sim._obj_xyz)
        seen[name] = _in_view(d, bearing, sim.camera, sim.detection_model.min_range)
    result: dict[str, float] = {}
    count = np.zeros(times.size)
    for a, b in combinations(sim.robots, 2):
        both = (seen[a] & seen[b]).any(axis=1)
        result[pair_key(a, b)] = float(both.mean())
        count += both
    result["any"] = float((count > 0).mean())
    result["mean_pairs"] = float(count.mean())
    return result


# ============================================================================ scenarios
def _polygon_loop(
    vertices: Sequence[tuple[float, float]], speed: float, turn_rate: float
) -> tuple[tuple[float, float, float], list[tuple[float, float, float]]]:
    """One loop of a closed polygon: drive each edge straight, turn in place at each corner.

    Returns the start pose (first vertex, heading along the first edge) and the segments.
    """
    P = np.asarray(vertices, dtype=float)
    n = len(P)
    edges = np.roll(P, -1, axis=0) - P
    headings = np.arctan2(edges[:, 1], edges[:, 0])
    segments: list[tuple[float, float, float]] = []
    for i in range(n):
        segments.append((float(np.hypot(*edges[i])) / speed, speed, 0.0))
        turn = float(wrap_angle(headings[(i + 1) % n] - headings[i]))
        if abs(turn) > 1e-9:
            segments.append((abs(turn) / turn_rate, 0.0, math.copysign(turn_rate, turn)))
    return (float(P[0, 0]), float(P[0, 1]), float(headings[0])), segments


def _circle_loop(
    cx: float, cy: float, radius: float, speed: float, start_angle: float = -math.pi / 2
) -> tuple[tuple[float, float, float], list[tuple[float, float, float]]]:
    """One counter-clockwise circle; starts at ``start_angle`` on it, heading along it."""
    x = cx + radius * math.cos(start_angle)
    y = cy + radius * math.sin(start_angle)
    return (x, y, start_angle + math.pi / 2), [(TWO_PI * radius / speed, speed, speed / radius)]


def _looped_motion(
    name: str,
    node: str,
    pattern: str,
    loop: tuple[tuple[float, float, float], list[tuple[float, float, float]]],
    *,
    seed: int,
    duration: float,
    initial_yaw: float | None,
    turn_rate: float,
    commanded: bool,
) -> RobotMotion:
    """Repeat a loop for the whole run, starting at a random point of it (seeded phase).

    With ``initial_yaw``, the robot starts with that heading and first turns in place onto
    the pattern; with ``None`` it starts heading along the pattern.
    """
    start, seg = loop
    period = sum(s[0] for s in seg)
    phase = float(_stream(seed, "phase", name).uniform(0.0, period))
    n_loops = math.ceil((phase + duration) / period) + 1
    full = np.asarray(seg * n_loops, dtype=float)
    traj = _Trajectory(*start)
    traj.extend(full[:, 0], full[:, 1], full[:, 2])
    x, y, yaw, _ = (float(a[0]) for a in traj.evaluate(np.array([phase])))
    # Cut the segment list at the phase.
    ends = np.cumsum(full[:, 0])
    k = int(np.searchsorted(ends, phase, side="right"))
    first = (float(ends[k] - phase), float(full[k, 1]), float(full[k, 2]))
    segments = [first, *(tuple(map(float, r)) for r in full[k + 1 :])]
    if initial_yaw is not None:
        turn = float(wrap_angle(yaw - initial_yaw))
        if abs(turn) > 1e-9:
            segments.insert(0, (abs(turn) / turn_rate, 0.0, math.copysign(turn_rate, turn)))
        yaw = initial_yaw
    return RobotMotion(
        name=name,
        node=node,
        x=x,
        y=y,
        yaw=float(wrap_angle(yaw)),
        segments=tuple(segments),  # type: ignore[arg-type]
        commanded=commanded,
        pattern=pattern,
    )


def _initial_yaw(seed: int, name: str, heading_offsets: str) -> float | None:
    if heading_offsets == "start":
        return None
    if heading_offsets == "random":
        return float(_stream(seed, "initial-yaw", name).uniform(-math.pi, math.pi))
    raise ValueError(f"heading_offsets must be 'start' or 'random', got {heading_offsets!r}")


def _place_objects(
    seed: int, nominal: Sequence[SimObject], jitter: float = 0.15
) -> list[SimObject]:
    """The nominal objects, each moved by up to ``jitter`` metres (seeded)."""
    rng = _stream(seed, "objects")
    offsets = rng.uniform(-jitter, jitter, size=(len(nominal), 2))
    return [
        SimObject(o.label, o.x + float(dx), o.y + float(dy), o.z)
        for o, (dx, dy) in zip(nominal, offsets, strict=True)
    ]


TURN_RATE = 0.6
"""Turn-in-place rate at pattern corners (rad/s)."""

MULTI_OBJECTS: tuple[SimObject, ...] = (
    SimObject("chair", 2.2, 0.7, 0.45),
    SimObject("chair", 0.0, 2.4, 0.45),
    SimObject("bottle", 0.25, -1.6, 0.75),
    SimObject("backpack", -2.7, 0.2, 0.25),
    SimObject("suitcase", 1.4, -0.2, 0.35),
    SimObject("potted plant", -2.5, 3.7, 0.5),
    SimObject("tv", 3.55, 3.2, 0.8),
    SimObject("cup", 4.4, -2.0, 0.75),
)
"""Nominal objects of the multi scenario (each moved by up to 0.15 m per seed).

Placed (by a small search over layouts, at least 0.45 m from every path) so that pairs of
robots see a common object at the same time for much of the run: with ideal cameras at least
one pair does about 90 % of the time, and about two pairs on average (see :func:`covisibility`).
"""


def multi_scenario(
    seed: int = 0,
    *,
    duration: float = 60.0,
    detections: bool = False,
    heading_offsets: Literal["start", "random"] = "start",
    uwb: UwbErrorModel | None = None,
    commanded: Sequence[str] = (),
    odometry: OdometryErrorModel | None = None,
    camera: DetectionErrorModel | None = None,
    actuation: ActuationModel | None = None,
) -> Simulation:
    """The paper's five-robot experiment in the 8 m x 9 m arena.

    ``r0`` (node ``n_0``) is static and the reference; ``r1`` drives a triangle, ``r2`` an X
    (both diagonals of a square joined by two of its sides), ``r3`` a circle and ``r4`` a
    rectangle, one per quarter of the arena, each 2-2.5 m across at 0.22-0.28 m/s, turning in
    place at the corners and looping until the end (each from a seeded point of its loop).

    ``heading_offsets="start"``: robots start heading along their pattern (``r0``, at (1.0, -0.6),
    faces 75 degrees); ``"random"``: every robot starts with a random heading (the moving
    ones first turn onto their pattern). Either way the odometry frame is the start pose, so
    the heading offset is the initial yaw, given truthfully in ``config``.
    Robots named in ``commanded`` start where their pattern would and obey
    :meth:`Simulation.set_command` instead.
    """
    unknown = set(commanded) - {"r0", "r1", "r2", "r3", "r4"}
    if unknown:
        raise ValueError(f"unknown commanded robot(s) {sorted(unknown)}; the team is r0..r4")
    loops = {
        "r1": (
            "triangle",
            _polygon_loop([(-3.2, 1.4), (-0.8, 1.4), (-2.0, 3.48)], 0.25, TURN_RATE),
        ),
        "r2": (
            "x",
            _polygon_loop([(1.0, 1.3), (3.0, 3.3), (3.0, 1.3), (1.0, 3.3)], 0.22, TURN_RATE),
        ),
        "r3": ("circle", _circle_loop(-2.0, -2.4, 1.1, 0.25)),
        "r4": (
            "rectangle",
            _polygon_loop([(0.8, -3.3), (3.2, -3.3), (3.2, -1.5), (0.8, -1.5)], 0.28, TURN_RATE),
        ),
    }
    yaw0 = _initial_yaw(seed, "r0", heading_offsets)
    motions = [
        RobotMotion(
            "r0",
            "n_0",
            1.0,
            -0.6,
            math.radians(75.0) if yaw0 is None else yaw0,
            commanded="r0" in commanded,
            pattern="static",
        )
    ]
    for i, (name, (pattern, loop)) in enumerate(loops.items(), start=1):
        motions.append(
            _looped_motion(
                name,
                f"n_{i}",
                pattern,
                loop,
                seed=seed,
                duration=duration,
                initial_yaw=_initial_yaw(seed, name, heading_offsets),
                turn_rate=TURN_RATE,
                commanded=name in commanded,
            )
        )
    return Simulation(
        motions,
        reference="r0",
        seed=seed,
        duration=duration,
        name="sim_multi" if not commanded else "sim_nav",
        objects=_place_objects(seed, MULTI_OBJECTS),
        detections=detections,
        uwb=uwb,
        odometry=odometry,
        camera=camera,
        actuation=actuation,
    )


SINGLE_OBJECTS: tuple[SimObject, ...] = (
    SimObject("chair", 0.5, 0.0, 0.45),
    SimObject("bottle", 0.0, 1.6, 0.75),
    SimObject("backpack", 0.2, -1.7, 0.25),
    SimObject("suitcase", -3.3, 0.0, 0.35),
)


def single_scenario(
    seed: int = 0,
    *,
    duration: float = 45.0,
    detections: bool = False,
    heading_offsets: Literal["start", "random"] = "start",
    uwb: UwbErrorModel | None = None,
    commanded: Sequence[str] = (),
    odometry: OdometryErrorModel | None = None,
    camera: DetectionErrorModel | None = None,
    actuation: ActuationModel | None = None,
) -> Simulation:
    """The single-range experiment: ``r0`` static (the reference), ``r1`` driving circles.

    ``r1`` drives counter-clockwise circles of 1 m radius at 0.22 m/s (about 10 m in 45 s,
    like the real recording) about 2.5 m from ``r0``; one UWB pair (``n_0-n_1``) at 10 Hz.
    """
    yaw0 = _initial_yaw(seed, "r0", heading_offsets)
    motions = [
        RobotMotion(
            "r0",
            "n_0",
            1.5,
            0.0,
            math.pi if yaw0 is None else yaw0,
            commanded="r0" in commanded,
            pattern="static",
        ),
        _looped_motion(
            "r1",
            "n_1",
            "circle",
            _circle_loop(-1.0, 0.0, 1.0, 0.22),
            seed=seed,
            duration=duration,
            initial_yaw=_initial_yaw(seed, "r1", heading_offsets),
            turn_rate=TURN_RATE,
            commanded="r1" in commanded,
        ),
    ]
    return Simulation(
        motions,
        reference="r0",
        seed=seed,
        duration=duration,
        name="sim_single",
        objects=_place_objects(seed, SINGLE_OBJECTS, jitter=0.1),
        detections=detections,
        uwb=uwb,
        odometry=odometry,
        camera=camera,
        actuation=actuation,
    )


def nav_scenario(
    seed: int = 0,
    *,
    robot: str = "r2",
    duration: float = 60.0,
    detections: bool = False,
    heading_offsets: Literal["start", "random"] = "start",
    uwb: UwbErrorModel | None = None,
    odometry: OdometryErrorModel | None = None,
    camera: DetectionErrorModel | None = None,
    actuation: ActuationModel | None = None,
) -> Simulation:
    """The multi team with ``robot`` (default ``r2``) driven by :meth:`Simulation.set_command`.

    For closed-loop navigation on the relative estimate: call :meth:`Simulation.advance` in
    steps, feed the events to the localizer, and command the robot from its estimate.
    """
    return multi_scenario(
        seed,
        duration=duration,
        detections=detections,
        heading_offsets=heading_offsets,
        uwb=uwb,
        commanded=(robot,),
        odometry=odometry,
        camera=camera,
        actuation=actuation,
    )
