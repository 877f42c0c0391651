"""One fixed-lag smoother of a flying team's poses, in GTSAM's ``Pose3``.

The state is one ``Pose3`` per robot per step, in a frame whose x-y origin and yaw are the
reference's first pose and whose z is up (the height above the ground where heights are
measured, else the reference's first height). Roll and pitch are taken as known and level
(the flight controller's attitude): every key's prior and every motion factor holds them at
zero within ``LEVEL_SIGMA``, so a key has four free coordinates, the 4-DoF state of a drone.

* **Motion**: per robot its odometry's displacement in its own body frame and its turn
  (:class:`Motion`), the turn less a constant gyro bias (a ``Vector1`` key per robot with
  odometry, kept in the window like the biases: a gyro's bias turns the whole formation in the
  robot's view); without odometry a random walk (a native ``BetweenFactorPose3``), and for a
  robot with no odometry at all (``blind``), on every three consecutive keys, a constant
  velocity: the change of the mean velocity and yaw rate between the two steps, of variance
  ``q (dt1 + dt2) / 3`` for a white acceleration of density ``q`` (``CV_ACCELERATION``,
  smaller vertically, ``CV_YAW_ACCELERATION``): what pools a drone's ranges over seconds where
  nothing measures its motion.
* **Ranges**: per tag pair ranged in the step one Huber-robust factor
  ``|X_a arm_a - X_b arm_b| + b - z`` between the two tags (a Python ``CustomFactor``: GTSAM's
  ``RangeFactorWithTransform`` carries one lever arm, a tag pair has two), the pair's online
  bias ``b`` where it has one, else the bias already removed from ``z``.
* **Heights**: ``z(X) - h`` per robot with a height in the step.
* **Online biases**: the 2D smoother's prior (:func:`~relloc.estimators.smoother.graph.add_bias_prior`),
  the keys stamped far in the future: kept in the window for the whole run.

The published pose of a robot is ``X_ref^-1 X_k``, its covariance from the window's joint
marginal of the two keys through the Jacobians of ``between`` (docs/explanation/flying.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from relloc.estimators.smoother.graph import HUBER_K, add_bias_prior
from relloc.localizers.priors import BiasPrior

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
Error = Callable[[gtsam.CustomFactor, gtsam.Values, list[FloatArray] | None], FloatArray]

LEVEL_SIGMA = 1e-3
"""Std (rad) of roll and pitch about level in every prior and motion factor."""
REFERENCE_SIGMA = 1e-4
"""Std (m, rad) of the prior that pins the reference's first key (x, y, yaw)."""
FREE_HEIGHT_SIGMA = 100.0
"""Std (m) of the reference's first height where heights are measured (they place it)."""
MARGINALISE_EVERY = 0.25
"""The fraction of the lag whose pose keys are marginalised together (:meth:`PoseWindow._stamp`):
the window then holds between the lag and 1.25 times it."""
RESTAMP_FRACTION = 0.4
"""The constant keys (biases, offsets, gyro biases) are re-stamped every this fraction of the
lag, so that the lag never marginalises them; not every step: a re-stamp makes iSAM2 re-order
and re-eliminate the window (every step: four times slower)."""
CV_ACCELERATION = 0.5
"""Density (m^2/s^3 per axis) of the white acceleration of a robot without odometry."""
CV_VERTICAL_ACCELERATION = 0.05
"""Density (m^2/s^3) of its vertical acceleration: a multirotor holds its height and changes it
slowly (thrust), where it turns and accelerates sideways freely; and the ranges of a level
formation see heights least (docs/explanation/flying.md)."""
CV_YAW_ACCELERATION = 0.05
"""Density (rad^2/s^3) of the white yaw acceleration of a robot without odometry."""
GYRO_BIAS_SIGMA = 0.003
"""Std (rad/s) of the prior of a robot's gyro bias (0.17 deg/s): a flight controller's gyro
after its start-up calibration, or a VIO's yaw drift. A broader prior lets the reference's yaw
bend within the window (0.01 rad/s: the formation 3-5 deg off for tens of seconds)."""


@dataclass(frozen=True)
class TagRanges:
    """One range per tag pair: the tags ``tag_a``/``tag_b``, their robots ``index_a``/``index_b``
    (team order) and lever arms ``arm_a``/``arm_b`` ``(K, 3)``, the distance less any fixed
    bias, its std, and the pair's online bias (its index among the smoother's bias keys, -1:
    none)."""

    tag_a: IntArray
    tag_b: IntArray
    index_a: IntArray
    index_b: IntArray
    arm_a: FloatArray
    arm_b: FloatArray
    distance: FloatArray
    sigma: FloatArray
    bias: IntArray

    @property
    def size(self) -> int:
        return int(self.index_a.size)


@dataclass(frozen=True)
class Motion:
    """Each robot's motion over a step of ``dt`` seconds: ``delta`` ``(N, 4)`` its displacement
    in its own body frame at the step's start and its turn ``(dx, dy, dz, dyaw)``, ``sigma``
    ``(N, 4)`` their stds, ``measured`` ``(N,)`` whether odometry measured it (its turn then
    less the robot's gyro bias times ``dt``), else a random walk."""

    delta: FloatArray
    sigma: FloatArray
    measured: NDArray[np.bool_]
    dt: float


def pose_of(row: FloatArray) -> gtsam.Pose3:
    """A level ``Pose3`` from ``(x, y, z, yaw)``."""
    return gtsam.Pose3(gtsam.Rot3.Yaw(float(row[3])), np.asarray(row[:3], float))


def row_of(pose: gtsam.Pose3) -> FloatArray:
    """``(x, y, z, yaw)`` of a ``Pose3``."""
    return np.array([*pose.translation(), pose.rotation().yaw()])


def _sigmas(sigma: FloatArray) -> gtsam.noiseModel.Base:
    """A ``Pose3`` noise (tangent ``[roll, pitch, yaw, x, y, z]``) from ``(sx, sy, sz, syaw)``."""
    return gtsam.noiseModel.Diagonal.Sigmas(
        np.array([LEVEL_SIGMA, LEVEL_SIGMA, sigma[3], sigma[0], sigma[1], sigma[2]], float)
    )


def _tag_range(distance: float, arm_a: FloatArray, arm_b: FloatArray) -> Error:
    """The error of a range between the tags at ``arm_a`` on key ``X_a`` and ``arm_b`` on
    ``X_b`` (keys ``(X_a, X_b)`` or ``(X_a, X_b, b)``): ``|t_a - t_b| + b - z``, ``t = X arm``.
    A right perturbation ``[w, v]`` of ``X`` moves its tag by ``R (v + w x arm)``, so with
    ``u`` the unit vector from ``t_b`` to ``t_a`` and ``c = R^T u`` the range's Jacobian is
    ``[arm x c, c]`` (called per factor per linearisation: plain floats, no small arrays)."""
    ax, ay, az = (float(v) for v in arm_a)
    bx, by, bz = (float(v) for v in arm_b)

    def error(
        factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[FloatArray] | None
    ) -> FloatArray:
        keys = factor.keys()
        xa, xb = values.atPose3(keys[0]), values.atPose3(keys[1])
        dx, dy, dz = (xa.transformFrom(arm_a) - xb.transformFrom(arm_b)).tolist()
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        if jacobians is not None:
            u = np.array([dx, dy, dz]) / dist if dist > 1e-9 else np.array([1.0, 0.0, 0.0])
            c1, c2, c3 = xa.rotation().unrotate(u).tolist()
            d1, d2, d3 = xb.rotation().unrotate(u).tolist()
            jacobians[0] = np.array(
                [[ay * c3 - az * c2, az * c1 - ax * c3, ax * c2 - ay * c1, c1, c2, c3]]
            )
            jacobians[1] = -np.array(
                [[by * d3 - bz * d2, bz * d1 - bx * d3, bx * d2 - by * d1, d1, d2, d3]]
            )
            if len(keys) > 2:
                jacobians[2] = _ONE
        bias = values.atVector(keys[2])[0] if len(keys) > 2 else 0.0
        return np.array([dist + bias - distance])

    return error


_ONE = np.ones((1, 1))


def _odometry(delta: FloatArray, dt: float) -> Error:
    """The error of an odometry step between keys ``(X_prev, X_new, g)``: the measured
    displacement and turn ``delta`` ``(dx, dy, dz, dyaw)``, the turn less the gyro bias ``g``
    times ``dt``, against ``X_prev^-1 X_new`` (GTSAM's between factor's error, in its tangent;
    the Jacobians are GTSAM's, the bias's ``d Delta / d g = [0, 0, -dt, 0, 0, 0]``)."""
    translation = np.asarray(delta[:3], float)
    turn = float(delta[3])
    d_bias = np.array([[0.0], [0.0], [-dt], [0.0], [0.0], [0.0]])

    def error(
        factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[FloatArray] | None
    ) -> FloatArray:
        k_prev, k_new, k_gyro = factor.keys()
        measured = gtsam.Pose3(gtsam.Rot3.Yaw(turn - values.atVector(k_gyro)[0] * dt), translation)
        if jacobians is None:
            return np.asarray(
                measured.localCoordinates(values.atPose3(k_prev).between(values.atPose3(k_new)))
            )
        h1, h2 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
        j1, j2 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
        moved = values.atPose3(k_prev).between(values.atPose3(k_new), h1, h2)
        out = np.asarray(measured.localCoordinates(moved, j1, j2))
        jacobians[0] = j2 @ h1
        jacobians[1] = j2 @ h2
        jacobians[2] = j1 @ d_bias
        return out

    return error


def _constant_velocity(dt1: float, dt2: float) -> Error:
    """The error of a robot's three consecutive keys ``(X_0, X_1, X_2)`` under a constant
    velocity: the change of its mean velocity and yaw rate between the two steps,
    ``(t_2 - t_1) / dt2 - (t_1 - t_0) / dt1`` (world axes) and the same of the yaw. A right
    perturbation ``[w, v]`` of a level key moves its translation by ``R v`` and its yaw by
    ``w_z``."""
    yaw_row = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])

    def error(
        factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[FloatArray] | None
    ) -> FloatArray:
        keys = factor.keys()
        poses = [values.atPose3(k) for k in keys]
        t0, t1, t2 = (p.translation() for p in poses)
        y0, y1, y2 = (p.rotation().yaw() for p in poses)
        out = np.empty(4)
        out[:3] = (t2 - t1) / dt2 - (t1 - t0) / dt1
        out[3] = math.remainder(y2 - y1, math.tau) / dt2 - math.remainder(y1 - y0, math.tau) / dt1
        if jacobians is not None:
            for j, scale in enumerate((1.0 / dt1, -1.0 / dt1 - 1.0 / dt2, 1.0 / dt2)):
                jac = np.zeros((4, 6))
                jac[:3, 3:] = scale * poses[j].rotation().matrix()
                jac[3] = scale * yaw_row
                jacobians[j] = jac
        return out

    return error


def _height(h: float) -> Error:
    """The error of a height ``h`` of key ``X``: ``z(X) - h``."""

    def error(
        factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[FloatArray] | None
    ) -> FloatArray:
        x = values.atPose3(factor.keys()[0])
        if jacobians is not None:
            jacobians[0] = np.concatenate([np.zeros(3), x.rotation().matrix()[2]]).reshape(1, 6)
        return np.array([x.translation()[2] - h])

    return error


def _cv_noise(dt1: float, dt2: float) -> gtsam.noiseModel.Base:
    """The constant-velocity factor's noise: white acceleration of density ``CV_ACCELERATION``
    (vertically ``CV_VERTICAL_ACCELERATION``, yaw ``CV_YAW_ACCELERATION``) changes two adjacent
    steps' mean velocities by a variance of ``q (dt1 + dt2) / 3``."""
    span = (dt1 + dt2) / 3.0
    q = np.array([CV_ACCELERATION, CV_ACCELERATION, CV_VERTICAL_ACCELERATION, CV_YAW_ACCELERATION])
    return gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(q * span))


class PoseWindow:
    """A fixed-lag smoother of ``n`` robots' level poses, ``reference`` the pinned one (module
    docstring)."""

    def __init__(
        self,
        n: int,
        reference: int,
        lag: float,
        biases: BiasPrior | None,
        gyros: NDArray[np.bool_] | None = None,
        *,
        blind: NDArray[np.bool_] | None = None,
    ) -> None:
        """``gyros``: which robots' odometry turns carry a gyro bias to estimate (none by
        default); ``blind``: which robots have no odometry at all, whose keys a constant
        velocity ties (none by default; not a robot with odometry whose yaw is still sought)."""
        self.n = n
        self.reference = reference
        self.others = np.array([i for i in range(n) if i != reference], dtype=np.intp)
        self.smoother = gtsam.IncrementalFixedLagSmoother(lag)
        self.step = -1
        self._lag = lag
        self.blind = np.zeros(n, bool) if blind is None else np.asarray(blind, bool)
        self._last_dt = 0.0
        """The previous step's length (s): the constant-velocity factors' first interval."""
        self._stamped = -np.inf
        self.prior = biases
        self.bias_mean = np.zeros(0) if biases is None else biases.mean
        self.bias_keys = [gtsam.symbol("b", j) for j in range(self.bias_mean.size)]
        latents = 0 if biases is None else biases.latent_sigma.size
        self.offset_keys = [gtsam.symbol("o", j) for j in range(latents)]
        self.gyro_keys = {
            int(i): gtsam.symbol("g", int(i))
            for i in np.flatnonzero(np.zeros(n, bool) if gyros is None else gyros)
        }
        """Each gyro bias's key, by robot."""
        self.poses: FloatArray = np.zeros((n, 4))
        """Each robot's latest ``(x, y, z, yaw)``."""
        self.biases: FloatArray = self.bias_mean.copy()
        self._estimate = gtsam.Values()
        self._joint: FloatArray | None = None

    def keys(self, step: int | None = None) -> list[int]:
        """The robots' keys at ``step`` (default: the latest), team order."""
        s = self.step if step is None else step
        return [gtsam.symbol("x", s * self.n + i) for i in range(self.n)]

    def start(
        self,
        t: float,
        poses: FloatArray,
        sigma: FloatArray,
        *,
        ranges: TagRanges,
        heights: dict[int, tuple[float, float]],
    ) -> None:
        """The first step at ``t``: robot ``i`` with a prior at ``poses[i]`` ``(x, y, z, yaw)``
        of stds ``sigma[i]`` (the reference's x, y and yaw pinned, its height free where
        heights are measured), the biases at their prior, the start's ranges and heights."""
        self.step = 0
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        keys = self.keys()
        for i, key in enumerate(keys):
            s = np.asarray(sigma[i], float)
            if i == self.reference:
                free = FREE_HEIGHT_SIGMA if heights else REFERENCE_SIGMA
                s = np.array([REFERENCE_SIGMA, REFERENCE_SIGMA, free, REFERENCE_SIGMA])
            graph.add(gtsam.PriorFactorPose3(key, pose_of(poses[i]), _sigmas(s)))
            values.insert(key, pose_of(poses[i]))
            stamps.insert((key, self._stamp(t)))
        if self.prior is not None:
            add_bias_prior(
                graph, values, stamps, self._stamp(t), self.prior, self.bias_keys, self.offset_keys
            )
        gyro_noise = gtsam.noiseModel.Isotropic.Sigma(1, GYRO_BIAS_SIGMA)
        for key in self.gyro_keys.values():
            graph.add(gtsam.PriorFactorVector(key, np.zeros(1), gyro_noise))
            values.insert(key, np.zeros(1))
            stamps.insert((key, self._stamp(t)))
        self._stamped = t
        self._last_dt = 0.0
        self._measurements(graph, keys, ranges, heights)
        self._update(graph, values, stamps)

    def advance(
        self,
        t: float,
        motion: Motion,
        *,
        ranges: TagRanges,
        heights: dict[int, tuple[float, float]],
    ) -> None:
        """The next step at ``t``: every robot moved by ``motion``, the step's ranges (one per
        tag pair) and heights (robot -> (median height, std))."""
        prev = self.keys()
        self.step += 1
        new = self.keys()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        for i in range(self.n):
            delta = pose_of(motion.delta[i])
            noise = _sigmas(motion.sigma[i])
            gyro = self.gyro_keys.get(i)
            if motion.measured[i] and gyro is not None:
                error = _odometry(motion.delta[i], motion.dt)
                graph.add(gtsam.CustomFactor(noise, [prev[i], new[i], gyro], error))
            else:
                graph.add(gtsam.BetweenFactorPose3(prev[i], new[i], delta, noise))
            values.insert(new[i], pose_of(self.poses[i]).compose(delta))
            stamps.insert((new[i], self._stamp(t)))
            if self.blind[i] and self.step >= 2 and self._last_dt > 0.0 < motion.dt:
                graph.add(
                    gtsam.CustomFactor(
                        _cv_noise(self._last_dt, motion.dt),
                        [self.keys(self.step - 2)[i], prev[i], new[i]],
                        _constant_velocity(self._last_dt, motion.dt),
                    )
                )
        self._last_dt = motion.dt
        if t - self._stamped >= RESTAMP_FRACTION * self._lag:  # constant keys kept in the lag
            for key in [*self.bias_keys, *self.offset_keys, *self.gyro_keys.values()]:
                stamps.insert((key, self._stamp(t)))
            self._stamped = t
        self._measurements(graph, new, ranges, heights)
        self._update(graph, values, stamps)

    def _stamp(self, t: float) -> float:
        """A pose key's stamp: ``t`` rounded up to ``MARGINALISE_EVERY`` of the lag, so that
        the lag marginalises the window's oldest keys in blocks, not every step (each
        marginalisation re-eliminates the window from the marginalised keys to the root)."""
        block = MARGINALISE_EVERY * self._lag
        return math.ceil(t / block) * block

    def _measurements(
        self,
        graph: gtsam.NonlinearFactorGraph,
        keys: list[int],
        ranges: TagRanges,
        heights: dict[int, tuple[float, float]],
    ) -> None:
        huber = gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K)
        for k in range(ranges.size):
            noise = gtsam.noiseModel.Robust.Create(
                huber, gtsam.noiseModel.Isotropic.Sigma(1, float(ranges.sigma[k]))
            )
            a, b, j = int(ranges.index_a[k]), int(ranges.index_b[k]), int(ranges.bias[k])
            factor_keys = [keys[a], keys[b], *([self.bias_keys[j]] if j >= 0 else [])]
            error = _tag_range(float(ranges.distance[k]), ranges.arm_a[k], ranges.arm_b[k])
            graph.add(gtsam.CustomFactor(noise, factor_keys, error))
        for i, (h, s) in heights.items():
            height_noise = gtsam.noiseModel.Isotropic.Sigma(1, s)
            graph.add(gtsam.CustomFactor(height_noise, [keys[i]], _height(h)))

    def _update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: gtsam.FixedLagSmootherKeyTimestampMap,
    ) -> None:
        self.smoother.update(graph, values, stamps)
        self._joint = None
        self._estimate = est = self.smoother.calculateEstimate()
        self.poses = np.array([row_of(est.atPose3(k)) for k in self.keys()])
        self.biases = np.array([est.atVector(k)[0] for k in self.bias_keys], float)

    def _window_joint(self) -> FloatArray:
        """The window's joint marginal covariance of ``[X_ref, X_others..., biases...,
        offsets...]`` (6 tangent rows per pose, ``[w, v]``; 1 per bias), once per update, from
        iSAM2's Bayes tree (no factor linearised again)."""
        if self._joint is None:
            keys = self.keys()
            order = [
                keys[self.reference],
                *(keys[i] for i in self.others),
                *self.bias_keys,
                *self.offset_keys,
            ]
            self._joint = self.smoother.getISAM2().jointMarginalCovariance(order).fullMatrix()
        return self._joint

    def relative(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Each non-reference robot in the reference's level body frame: ``(x, y, z, yaw)``
        ``(N-1, 4)``, the position's covariance ``(N-1, 3, 3)`` and the yaw's variance
        ``(N-1,)``. ``T = X_ref^-1 X_k`` perturbs as ``-Ad(T^-1) d_ref + d_k`` in its tangent;
        its position moves by ``R_T v``."""
        joint = self._window_joint()
        xr = self._estimate.atPose3(self.keys()[self.reference])
        rel = np.empty((self.others.size, 4))
        cov = np.empty((self.others.size, 3, 3))
        yaw_var = np.empty(self.others.size)
        for slot, i in enumerate(self.others.tolist(), start=1):
            t = xr.between(self._estimate.atPose3(self.keys()[i]))
            j = np.hstack([-t.inverse().AdjointMap(), np.eye(6)])
            rows = np.r_[0:6, 6 * slot : 6 * slot + 6]
            sigma = j @ joint[np.ix_(rows, rows)] @ j.T
            rot = t.rotation().matrix()
            rel[slot - 1] = row_of(t)
            cov[slot - 1] = rot @ sigma[3:, 3:] @ rot.T
            yaw_var[slot - 1] = sigma[2, 2]
        return rel, 0.5 * (cov + cov.transpose(0, 2, 1)), yaw_var

    def bias_std(self) -> FloatArray:
        """Std of each online bias (the window's marginal)."""
        start = 6 * self.n
        tail = np.diag(self._window_joint())[start : start + len(self.bias_keys)]
        return np.sqrt(np.maximum(tail, 0.0))

    def bias_joint(self) -> FloatArray:
        """The joint covariance of the online biases and then the shared offsets (the
        window's marginal) ``(B + L, B + L)``."""
        return self._window_joint()[6 * self.n :, 6 * self.n :]

    def positions_at(self, step: int) -> FloatArray | None:
        """Every robot's ``(x, y, z)`` at ``step`` if the window still holds its keys (the
        estimate of the last update: no new solve per step asked)."""
        est = self._estimate
        keys = self.keys(step)
        if not all(est.exists(k) for k in keys):
            return None
        return np.array([est.atPose3(k).translation() for k in keys])

    def relative_at(self, step: int) -> FloatArray | None:
        """Each non-reference robot's ``(x, y, z, yaw)`` in the reference's level body frame at
        ``step`` ``(N-1, 4)`` as the window estimates it now (smoothed by every measurement
        since); ``None`` where the window no longer holds the step's keys."""
        est = self._estimate
        keys = self.keys(step)
        if not all(est.exists(k) for k in keys):
            return None
        xr = est.atPose3(keys[self.reference])
        return np.array([row_of(xr.between(est.atPose3(keys[i]))) for i in self.others.tolist()])

    def offset_estimates(self) -> tuple[list[float], list[float]]:
        """Each shared offset's estimate and std (the window's marginal)."""
        if not self.offset_keys:
            return [], []
        mean = [float(self._estimate.atVector(k)[0]) for k in self.offset_keys]
        tail = np.diag(self._window_joint())[6 * self.n + len(self.bias_keys) :]
        return mean, np.sqrt(np.maximum(tail, 0.0)).tolist()

    def cost(self) -> float:
        """The graph's error at the estimate: compares hypotheses over the same measurements."""
        return float(self.smoother.getFactors().error(self._estimate))
