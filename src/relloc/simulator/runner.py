"""The simulation: a team's ground-truth motion and sensors, as an event source.

:class:`Simulation` produces exactly the events a real recording or a live team produces
(:mod:`relloc.events`): odometry at 20 Hz per robot in the robot's *own* odometry frame (its pose
at ``t = 0``), UWB ranges for every pair of transceivers, detections of static objects by each
robot's forward camera at about 5 Hz, in the body frame, and ground truth ("motion capture") at
20 Hz in the world frame; the sensor errors are those of :mod:`relloc.simulator.error_models`.

* **Stable under change.** All sensor time stamps and noise draws are fixed when the simulation
  is built, each from its own stream (:mod:`relloc.simulator.streams`), so the step-wise API
  (:meth:`Simulation.advance`) returns the same events however the run is cut into steps.
* **Truthful configuration.** :attr:`Simulation.config` is the team configuration a user would
  write for this team: UWB node ids, true per-pair biases, true heading offsets (the paper's
  compass). What a real team would *not* know (wheel scales, gyro biases, the
  orientation-dependent range error) stays in the simulation, as attributes for tests.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from operator import attrgetter

import numpy as np
from numpy.typing import ArrayLike, NDArray

from relloc import geometry
from relloc.config import (
    CameraConfig,
    FilterConfig,
    PairCalibration,
    RobotConfig,
    TagConfig,
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
    SightingEvent,
)
from relloc.odometry import wrap_angle
from relloc.sensors.registry import registered
from relloc.simulator.error_models import (
    ActuationModel,
    DetectionErrorModel,
    OdometryErrorModel,
    SightingSensorModel,
    UwbErrorModel,
    camera_view,
    in_view,
)
from relloc.simulator.kinematics import (
    RobotMotion,
    SimObject,
    Trajectory,
    accumulate,
    arc_displacement,
)
from relloc.simulator.schedules import (
    draw_actuation,
    draw_camera,
    draw_odometry,
    draw_sightings,
    draw_uwb,
)

__all__ = ["ARENA", "SIM_PARTICLES", "Simulation"]

FloatArray = NDArray[np.float64]

ARENA: tuple[float, float, float, float] = (-4.0, 4.0, -4.5, 4.5)
"""The TIERS arena (xmin, xmax, ymin, ymax), about 8 m x 9 m."""

SIM_PARTICLES = 20000
"""Particle count of the simulated teams' filter (see ``Simulation.config``)."""
GYRO_BIAS_SIGMA = 0.002
"""Prior std of each robot's heading drift rate in the simulated teams' config (rad/s,
``[filter.self_calibration] gyro_bias_sigma``): what a gyro's data sheet would say, above the
simulator's uniform draw of at most ``OdometryErrorModel.gyro_bias_max``."""


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
        sightings: Sequence[SightingSensorModel] = (),
        odometry_topics: bool = True,
    ) -> None:
        """``odometry_topics`` False: the robots report no odometry (a UWB-only team)."""
        if duration <= 0:
            raise ValueError(f"duration must be positive, got {duration}")
        self.seed = int(seed)
        self.duration = float(duration)
        self.motions: tuple[RobotMotion, ...] = tuple(robots)
        self.robots: tuple[str, ...] = tuple(m.name for m in self.motions)
        self.commanded: tuple[str, ...] = tuple(m.name for m in self.motions if m.commanded)
        self.reference = reference
        self.odometry_topics = odometry_topics
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
        self._base_traj: dict[str, Trajectory] = {}
        for m in self.motions:
            traj = Trajectory(m.x, m.y, m.yaw)
            if not m.commanded and m.segments:
                d, v, w = np.asarray(m.segments, dtype=float).T
                traj.extend(d, v, w)
            self._base_traj[m.name] = traj
        self.true_heading_offsets: dict[str, float] = {
            m.name: float(wrap_angle(m.yaw)) for m in self.motions
        }

        self.true_odom_scales, self.true_gyro_biases, self._odom = draw_odometry(
            self.seed, self.motions, self.odometry_model, self.duration
        )
        self.true_biases, self._uwb = draw_uwb(
            self.seed, self.motions, self.uwb_model, self.duration
        )
        self._cam = (
            draw_camera(
                self.seed, self.motions, self.detection_model, len(self.sim_objects), self.duration
            )
            if self.detections_enabled
            else {}
        )
        self._act = draw_actuation(self.seed, self.commanded, self.actuation_model, self.duration)
        self.sighting_models: tuple[SightingSensorModel, ...] = tuple(sightings)
        self._sight = draw_sightings(self.seed, self.robots, self.sighting_models, self.duration)
        self._gt_times = np.arange(0.0, self.duration + 1e-9, 0.05)

        robot_cfgs = tuple(
            RobotConfig(
                name=m.name,
                uwb_node="" if m.tags else m.node,
                tags=tuple(TagConfig(node, arm) for node, arm in m.tags),
                odom_topic=f"/{m.name}/odom" if odometry_topics else "",  # sim-robots' topic
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
            # ambiguity of the uniform start resolves quickly and fewer particles than the
            # mostly static recordings need will do (docs/explanation/measurements.md, "Measurements moved
            # from the code").
            # The reference's odometry heading drifts as much as every other robot's (one
            # gyro model for the team): its heading walk is the others' (see SIM_PARTICLES
            # for the particles, docs/explanation/self-calibration.md, "The floor"); every
            # simulated gyro has a constant bias, held as a state (GYRO_BIAS_SIGMA).
            filter=FilterConfig(particles=SIM_PARTICLES).with_changes(
                reference_heading_walk=FilterConfig().self_calibration.heading_walk,
                gyro_bias_sigma=GYRO_BIAS_SIGMA,
            ),
        )
        self._runner = _Runner(self)

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
        self._sightings(t0, t_until, out)
        for plugin in registered():
            out += plugin.simulate(self.sim, t0, t_until)
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
                GroundTruthEvent(t, name, (xi, yi), th)
                for t, xi, yi, th in zip(
                    times.tolist(), x.tolist(), y.tolist(), yaw.tolist(), strict=True
                )
            )

    def _odometry(self, t0: float, t1: float, out: list[Event]) -> None:
        if not self.sim.odometry_topics:
            return
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
            scale = om.scale_at(self.sim.true_odom_scales[name], times)
            v_m = scale * ds / dt + moving * om.sigma_v * od["nv"][i0:i1]
            w_m = dyaw / dt + moving * (
                self.sim.true_gyro_biases[name] + om.sigma_w * od["nw"][i0:i1]
            )
            yaw_end = accumulate(oyaw, w_m * dt)
            dx, dy = arc_displacement(yaw_end - w_m * dt, v_m, w_m, dt)
            xs, ys = accumulate(ox, dx), accumulate(oy, dy)
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
            ta, tb = _tag(pa, pair.arm_a), _tag(pb, pair.arm_b)
            dist = np.hypot(tb[0] - ta[0], tb[1] - ta[1])
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
            d, bearing = camera_view(x, y, yaw, cam, sim._obj_xyz)
            visible = in_view(d, bearing, cam, dm.min_range) & ~cd["miss"][i0:i1]
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

    def _sightings(self, t0: float, t1: float, out: list[Event]) -> None:
        for sm, obs, tgt, d in self.sim._sight:
            i0, i1 = np.searchsorted(d["t"], [t0, t1], side="right")
            if i1 <= i0:
                continue
            times = d["t"][i0:i1]
            xo, yo, yaw, _ = self.traj[obs].evaluate(times)
            xt, yt, _, _ = self.traj[tgt].evaluate(times)
            dist = np.hypot(xt - xo, yt - yo)
            bearing = wrap_angle(np.arctan2(yt - yo, xt - xo) - yaw)
            half = math.radians(sm.fov_deg) / 2.0
            seen = (np.abs(bearing) <= half) & (dist <= sm.max_range) & ~d["miss"][i0:i1]
            b_m = np.where(
                d["outlier"][i0:i1],
                2.0 * half * d["wild"][i0:i1],
                bearing + sm.sigma_bearing * d["nb"][i0:i1],
            )
            b_m = wrap_angle(b_m)
            r_m = np.maximum(dist + sm.sigma_range * d["nr"][i0:i1], 0.01)
            for k in np.flatnonzero(seen):
                out.append(
                    SightingEvent(
                        float(times[k]),
                        obs,
                        tgt,
                        float(r_m[k]) if sm.ranges else None,
                        float(b_m[k]),
                        sm.sigma_range,
                        sm.sigma_bearing,
                        sm.sensor,
                    )
                )


def _window(times: FloatArray, t0: float, t1: float) -> FloatArray:
    """The sorted ``times`` in ``(t0, t1]``."""
    i0, i1 = np.searchsorted(times, [t0, t1], side="right")
    return times[i0:i1]


def _tag(pose: tuple[FloatArray, ...], arm: tuple[float, float]) -> tuple[FloatArray, ...]:
    """Where a tag at ``arm`` (body frame) is at ``pose`` ``(x, y, yaw)``: the pose itself for
    a tag at the body origin (one-tag teams' ranges stay as they were, to the bit)."""
    if arm == (0.0, 0.0):
        return pose
    x, y = geometry.tag_position(np.stack([pose[0], pose[1]], axis=-1), pose[2], arm).T
    return x, y, pose[2]
