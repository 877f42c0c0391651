"""How the simulated sensors (and the actuators of commanded robots) differ from the truth.

* :class:`UwbErrorModel`: a per-pair bias, an error that depends smoothly on each end's heading
  relative to the bearing to the other end (antenna pattern and body occlusion, see
  :func:`antenna_gain`), Gaussian noise, positive NLOS spikes and dropouts, each pair at its own
  rate with its own phase and jitter; :class:`UwbPair` is one pair's drawn parameters.
* :class:`OdometryErrorModel`: a per-robot wheel-scale error, velocity noise and a small gyro
  bias make odometry drift like real wheel odometry.
* :class:`DetectionErrorModel`: a forward camera's field of view and range
  (:func:`camera_view`, :func:`in_view`), depth noise growing with distance, misses.
* :class:`SightingSensorModel`: a sensor that sees teammates in the observer's body frame
  (UWB angle of arrival beside the ranges, :data:`UWB_AOA`; a camera with a field of view,
  :data:`TEAMMATE_CAMERA`): field of view, range limit, Gaussian range and bearing noise and
  a share of gross outliers (a reflection, a misread marker).
* :class:`ActuationModel`: how a commanded robot's motion differs from its command.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from relloc.config import CameraConfig
from relloc.odometry import wrap_angle

FloatArray = NDArray[np.float64]


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
    error can differ from its bias, most for pairs with the static robot: what a learned
    correction can remove.
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
    scale_step: tuple[float, float] = (math.inf, 1.0)
    """``(t, factor)``: from ``t`` (s from the start) on, every robot's wheel scale is
    multiplied by ``factor`` (a tyre change, a load, a floor that makes the wheels slip)."""

    def scale_at(self, scale: float, t: FloatArray) -> FloatArray:
        """The wheel scale ``scale`` at times ``t`` (after :attr:`scale_step`)."""
        step_t, factor = self.scale_step
        return np.where(t >= step_t, scale * factor, scale)


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


@dataclass(frozen=True, eq=False)
class UwbPair:
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
    arm_a: tuple[float, float] = (0.0, 0.0)
    """Lever arm of node a on robot a (body frame, m)."""
    arm_b: tuple[float, float] = (0.0, 0.0)
    """Lever arm of node b on robot b."""

    def orientation_term(
        self, pa: tuple[FloatArray, ...], pb: tuple[FloatArray, ...]
    ) -> FloatArray:
        """Heading-dependent range error for poses ``pa``, ``pb`` (see :class:`UwbErrorModel`)."""
        bearing_ab = np.arctan2(pb[1] - pa[1], pb[0] - pa[0])
        alpha_a = pa[2] - bearing_ab - self.antenna[0]
        alpha_b = pb[2] - (bearing_ab + math.pi) - self.antenna[1]
        gain_a, gain_b = antenna_gain(alpha_a), antenna_gain(alpha_b)
        return self.amplitude[0] * gain_a + self.amplitude[1] * gain_b


def antenna_gain(alpha: FloatArray) -> FloatArray:
    """Shape of the heading-dependent error: +1.3 with the other end behind, zero mean."""
    return -np.cos(alpha) + 0.3 * np.cos(2.0 * alpha)


def camera_view(
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


def in_view(d: FloatArray, bearing: FloatArray, cam: CameraConfig, min_range: float) -> NDArray:
    """Whether objects at ``(d, bearing)`` from the camera are in its field of view and range."""
    half_fov = 0.5 * math.radians(cam.fov_deg)
    return (d <= cam.max_range) & (d >= min_range) & (np.abs(bearing) <= half_fov)


@dataclass(frozen=True)
class SightingSensorModel:
    """A sensor on every robot that sees its teammates in its body frame.

    At ``rate_hz`` (its own phase per ordered pair) the observer reports each teammate inside
    its field of view (``fov_deg`` wide, centred on its forward axis) and ``max_range``: the
    bearing with ``N(0, sigma_bearing^2)`` noise and, if ``ranges``, the range with
    ``N(0, sigma_range^2)``; with ``outlier_probability`` the bearing is instead uniform over
    the field of view (a reflection, a misread marker). Seen a teammate is missed with
    ``miss_probability``. Occlusion by other robots is not simulated.
    """

    sensor: str = "uwb_aoa"
    rate_hz: float = 10.0
    fov_deg: float = 120.0
    max_range: float = 10.0
    ranges: bool = False
    """Whether it measures the range too (a camera); UWB AoA is bearing only here, its range
    is the UWB range beside it."""
    sigma_range: float = 0.05
    sigma_bearing: float = math.radians(5.0)
    outlier_probability: float = 0.02
    miss_probability: float = 0.05


UWB_AOA = SightingSensorModel()
"""Phase-difference angle of arrival of a DW3000-class UWB radio: bearing only, 5 deg noise,
a 120 deg field of view in front of the antenna pair, at the UWB rate."""

TEAMMATE_CAMERA = SightingSensorModel(
    "camera",
    rate_hz=5.0,
    fov_deg=70.0,
    max_range=6.0,
    ranges=True,
    sigma_range=0.08,
    sigma_bearing=math.radians(1.0),
    outlier_probability=0.01,
    miss_probability=0.1,
)
"""A forward camera reading teammates' markers: range and bearing, 70 deg field of view."""
