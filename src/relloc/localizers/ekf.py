"""The classical cooperative-localization baseline: one centralised EKF over every robot's pose.

Roumeliotis and Bekey ("Distributed multirobot localization", IEEE T-RA 18(5), 2002) write the
team's state as all ``N`` poses ``(x_i, y_i, theta_i)`` in one world frame, ``3N`` numbers,
propagate each robot with its own odometry and update the joint covariance with every relative
measurement between two robots: the correlations it builds are what lets one robot's sighting
correct a teammate it never saw. Here:

* **Prediction.** Each robot's odometry displacement since the last step, in its body frame at
  the start of the step (``delta``, ``dpsi``), moves its pose: ``p += R(theta) delta``,
  ``theta += dpsi``; the Jacobian turns the heading uncertainty into position uncertainty.
  Noise: ``NOISE_PER_M`` per metre and ``PROCESS_NOISE`` per sqrt(s) on the displacement,
  ``NOISE_PER_RAD`` per radian turned (:mod:`relloc.filter.motion`) and the heading random walk
  ``heading_walk`` per sqrt(s) (:class:`relloc.config.SelfCalibrationConfig`).
* **Update.** A sighting of ``j`` by ``i`` is ``r = |p_j - p_i|``, ``b = atan2(.) - theta_i``
  (bearing innovation wrapped), with the sighting's own noise; a UWB range is ``|p_j - p_i|``
  plus the pair's calibrated bias. An innovation beyond a chi-square gate (99.9 %) is counted
  (``ekf_gated``) and not fused: the EKF has no robust tail.
* **Oracle start.** The state starts at the ground-truth poses (``initial_poses``, with a small
  covariance): the EKF is linearised and cannot start from a uniform prior. That is an
  **oracle**, which is why the method is called ``ekf_oracle``; relloc's filters start from
  nothing. It is the peer that the MRCLAM literature reports.

Estimates are each robot's position relative to the reference in the world frame (the shared
heading frame of an oracle start); the reference's heading goes to :attr:`odometry_yaws`, so the
body-frame evaluation turns them into the reference's body frame.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.estimate import Covariance, Estimate, Position
from relloc.events import RangeEvent, SightingEvent
from relloc.filter.motion import NOISE_PER_M, NOISE_PER_RAD, PROCESS_NOISE
from relloc.localizers.base import Localizer, Measurement

FloatArray = NDArray[np.float64]

GATE_CHI2 = {1: 10.83, 2: 13.82}
"""Chi-square 99.9 % quantiles by measurement dimension."""
START_SIGMA = (0.01, 0.01, math.radians(0.5))
"""Standard deviation of the oracle start (x, y in m; heading in rad)."""


class EkfOracleLocalizer(Localizer):
    """A centralised EKF over all poses, started at the ground truth (module docstring)."""

    method = "ekf_oracle"

    def __init__(
        self, config: TeamConfig, initial_poses: dict[str, tuple[float, float, float]]
    ) -> None:
        super().__init__(config)
        missing = [r for r in config.robot_names if r not in initial_poses]
        if missing:
            raise ValueError(f"ekf_oracle needs a start pose for every robot; missing {missing}")
        n = len(config.robot_names)
        self.x = np.zeros(3 * n)
        for i, r in enumerate(config.robot_names):
            self.x[3 * i : 3 * i + 3] = initial_poses[r]
        self.P = np.diag(np.tile(np.square(START_SIGMA), n))
        self.t = math.nan
        self._anchor: dict[str, tuple[float, float, float]] = {}

    def _track_frame(self, robot: str) -> tuple[float, float]:
        """The EKF takes body-frame increments: the track's frame does not matter, only its
        scale."""
        return 0.0, self.config.robot(robot).odom_scale

    # ---------------------------------------------------------------- prediction
    def _predict(self, t: float) -> None:
        walk = self.config.filter.self_calibration.heading_walk
        dt = 0.0 if math.isnan(self.t) else max(t - self.t, 0.0)
        self.t = t
        n = len(self.layout.robots)
        F = np.eye(3 * n)
        Q = np.zeros((3 * n, 3 * n))
        for i, robot in enumerate(self.layout.robots):
            track = self.tracks[robot]
            if track.empty:
                continue
            x1, y1, yaw1, _ = track.pose_at(t)
            if robot not in self._anchor:  # the start pose is the truth at its first odometry
                first = track.pose_at(self.first_odometry[robot][0])
                self._anchor[robot] = (first[0], first[1], first[2])
            before = self._anchor[robot]
            self._anchor[robot] = (x1, y1, yaw1)
            x0, y0, yaw0 = before
            c0, s0 = math.cos(yaw0), math.sin(yaw0)
            dx, dy = x1 - x0, y1 - y0
            fwd, left = c0 * dx + s0 * dy, -s0 * dx + c0 * dy
            dpsi = math.remainder(yaw1 - yaw0, math.tau)
            k = 3 * i
            th = self.x[k + 2]
            c, s = math.cos(th), math.sin(th)
            self.x[k] += c * fwd - s * left
            self.x[k + 1] += s * fwd + c * left
            self.x[k + 2] = math.remainder(th + dpsi, math.tau)
            F[k, k + 2] = -s * fwd - c * left
            F[k + 1, k + 2] = c * fwd - s * left
            dist = math.hypot(fwd, left)
            var_d = (NOISE_PER_M * dist) ** 2 + PROCESS_NOISE**2 * dt
            Q[k, k] = Q[k + 1, k + 1] = var_d
            Q[k + 2, k + 2] = (NOISE_PER_RAD * abs(dpsi)) ** 2 + walk**2 * dt
        self.P = F @ self.P @ F.T + Q

    # ---------------------------------------------------------------- update
    def _fuse(
        self, z: FloatArray, h: FloatArray, H: FloatArray, R: FloatArray, angle: list[bool]
    ) -> None:
        nu = z - h
        for k, is_angle in enumerate(angle):
            if is_angle:
                nu[k] = math.remainder(nu[k], math.tau)
        S = H @ self.P @ H.T + R
        if float(nu @ np.linalg.solve(S, nu)) > GATE_CHI2[len(z)]:
            self.stats["ekf_gated"] += 1
            return
        K = self.P @ H.T @ np.linalg.inv(S)
        self.x = self.x + K @ nu
        for i in range(len(self.layout.robots)):
            self.x[3 * i + 2] = math.remainder(self.x[3 * i + 2], math.tau)
        eye = np.eye(len(self.x))
        self.P = (eye - K @ H) @ self.P @ (eye - K @ H).T + K @ R @ K.T  # Joseph form

    def _geometry(self, i: int, j: int) -> tuple[float, float, float, float]:
        dx = self.x[3 * j] - self.x[3 * i]
        dy = self.x[3 * j + 1] - self.x[3 * i + 1]
        return dx, dy, max(math.hypot(dx, dy), 1e-6), self.x[3 * i + 2]

    def _sighting(self, ev: SightingEvent) -> None:
        i, j = self.layout.index(ev.observer), self.layout.index(ev.target)
        dx, dy, r, th = self._geometry(i, j)
        rows_z, rows_h, rows_H, var, angle = [], [], [], [], []
        if ev.range is not None:
            row = np.zeros(len(self.x))
            row[3 * j : 3 * j + 2] = (dx / r, dy / r)
            row[3 * i : 3 * i + 2] = (-dx / r, -dy / r)
            rows_z.append(ev.range)
            rows_h.append(r)
            rows_H.append(row)
            var.append(ev.sigma_range**2)
            angle.append(False)
        if ev.bearing is not None:
            row = np.zeros(len(self.x))
            row[3 * j : 3 * j + 2] = (-dy / r**2, dx / r**2)
            row[3 * i : 3 * i + 2] = (dy / r**2, -dx / r**2)
            row[3 * i + 2] = -1.0
            rows_z.append(ev.bearing)
            rows_h.append(math.atan2(dy, dx) - th)
            rows_H.append(row)
            var.append(ev.sigma_bearing**2)
            angle.append(True)
        self._fuse(np.array(rows_z), np.array(rows_h), np.array(rows_H), np.diag(var), angle)

    def _range(self, ev: RangeEvent) -> None:
        i, j = self.layout.index(ev.robot_a), self.layout.index(ev.robot_b)
        dx, dy, r, _ = self._geometry(i, j)
        bias, scale, _ = self.config.uwb.calibration(*self.config.range_nodes(ev))
        row = np.zeros(len(self.x))
        row[3 * j : 3 * j + 2] = (dx / r, dy / r)
        row[3 * i : 3 * i + 2] = (-dx / r, -dy / r)
        sigma = self.config.uwb.sigma
        self._fuse(
            np.array([ev.distance]),
            np.array([scale * r + bias]),
            scale * row[None, :],
            np.array([[sigma**2]]),
            [False],
        )

    # ---------------------------------------------------------------- one batch
    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        self._predict(t)
        for ev in sorted(batch, key=lambda e: e.t):
            if isinstance(ev, SightingEvent):
                self._sighting(ev)
            elif isinstance(ev, RangeEvent):
                self._range(ev)
            else:
                self.stats["ekf_ignored_" + type(ev).__name__] += 1
        return self._estimate(t)

    def _estimate(self, t: float) -> Estimate:
        lay = self.layout
        ref = lay.index(lay.reference)
        positions: dict[str, Position] = {}
        covs: dict[str, Covariance] = {}
        for robot in lay.others:
            j = lay.index(robot)
            positions[robot] = (
                float(self.x[3 * j] - self.x[3 * ref]),
                float(self.x[3 * j + 1] - self.x[3 * ref + 1]),
            )
            J = np.zeros((2, len(self.x)))
            J[:, 3 * j : 3 * j + 2] = np.eye(2)
            J[:, 3 * ref : 3 * ref + 2] = -np.eye(2)
            c = J @ self.P @ J.T
            covs[robot] = ((float(c[0, 0]), float(c[0, 1])), (float(c[1, 0]), float(c[1, 1])))
        yaws = self.odometry_yaws.setdefault(lay.reference, deque(maxlen=200_000))
        yaws.append((t, float(self.x[3 * ref + 2])))
        est = Estimate(t, self.method, lay.reference, positions, covs)
        self.last_estimate = est
        return est
