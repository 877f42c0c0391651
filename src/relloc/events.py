"""Measurement events: the only vocabulary shared by sources, stages and the localizer.

Every source (the simulator, a rosbag2 file, live Zenoh subscriptions) turns what it reads into
these small immutable records, each stamped with a time in seconds (header stamps, one clock
for the whole team) and the names of the robots it concerns. The localizer never learns where
an event came from, so offline evaluation and the live engine run exactly the same code.

Frames
------
* ``OdometryEvent`` carries the robot's pose in its *own* odometry frame (``odom``) and its
  body-frame twist. Putting it into the team's shared heading frame (heading offset, scale,
  pose-vs-twist integration) is the job of :mod:`relloc.odometry`, configured per robot.
* ``RangeEvent`` carries the UWB node ids as well as the robots: range biases belong to the
  transceivers, not to the robot names.
* ``DetectionEvent`` carries object positions in the robot's body frame (``base_link``, x
  forward, y left, z up); the source applies the camera extrinsics from the team config.
* ``SightingEvent`` carries a teammate seen in the observer's body frame (x forward, bearing
  counter-clockwise from x): a camera reading a teammate's marker, or a UWB radio's angle of
  arrival. Its noise is the source's (each sensor sets its own).
* ``HeightEvent`` is a robot's height above the ground (a flying robot's range finder).
* ``GroundTruthEvent`` is motion capture in the world frame, for evaluation only: the localizer
  ignores it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import NamedTuple


@dataclass(frozen=True, slots=True)
class OdometryEvent:
    """Pose of ``robot`` in its own odometry frame and its body-frame twist at time ``t``."""

    t: float
    robot: str
    x: float
    y: float
    yaw: float
    v: float = 0.0
    """Forward speed along the body x axis (m/s)."""
    w: float = 0.0
    """Yaw rate (rad/s)."""
    z: float = 0.0
    """Height in the odometry frame (m, z up): a flying robot's odometry (VIO, a flight
    controller's); 0 for a ground robot's."""


@dataclass(frozen=True, slots=True)
class RangeEvent:
    """A UWB range between the transceivers carried by ``robot_a`` and ``robot_b``."""

    t: float
    robot_a: str
    robot_b: str
    distance: float
    node_a: str = ""
    node_b: str = ""
    corrected: bool = False
    """True once a range-correction stage removed the pair's error (the filter then applies no
    bias of its own)."""
    sigma: float | None = None
    """Standard deviation (m) of this range's remaining error after a range-correction stage
    changed it: of ``distance - true distance`` when ``corrected`` is True, of
    ``distance - true distance - the pair's bias`` (the bias the filter still applies) when the
    stage removed only the orientation/motion part and left ``corrected`` False. Set by the
    stage from its model's uncertainty (or, for a pair whose model fell back to the constant,
    the constant's validation RMSE); ``None``: no estimate. The range model takes the larger of
    this and its configured sigma, so an unsure correction weighs less and a confident one never
    more than an uncorrected range (:func:`relloc.filter.ranges.RangeBatch.build`)."""

    @property
    def node_pair(self) -> str:
        """Canonical key of the transceiver pair (sorted node ids), e.g. ``"n_3-n_7"``."""
        a, b = self.node_a or self.robot_a, self.node_b or self.robot_b
        return pair_key(a, b)


@dataclass(frozen=True, slots=True)
class ObjectDetection:
    """One object seen by a robot's camera, position in the robot's body frame (m)."""

    label: str
    x: float
    y: float
    z: float = 0.0
    score: float = 1.0


@dataclass(frozen=True, slots=True)
class DetectionEvent:
    """All objects one robot's camera reported in one frame captured at time ``t``."""

    t: float
    robot: str
    objects: tuple[ObjectDetection, ...] = field(default_factory=tuple)


@dataclass(frozen=True, slots=True)
class GroundTruthEvent:
    """Motion-capture pose of ``robot`` in the world frame (evaluation only)."""

    t: float
    robot: str
    position: tuple[float, ...]
    """World-frame position (m), one entry per dimension: ``(x, y)`` in 2D, ``(x, y, z)`` where
    the motion capture's height is kept."""
    yaw: float = 0.0


@dataclass(frozen=True, slots=True)
class HeightEvent:
    """``robot``'s body origin at height ``z`` (m) above the team's ground plane (world z, up):
    a downward range finder or a barometer referenced to the ground. Only a 3D estimator
    fuses it; a 2D one counts it as ignored."""

    t: float
    robot: str
    z: float
    sigma: float = 0.05
    """The sensor's noise (m)."""


@dataclass(frozen=True, slots=True)
class RelativeObservation:
    """A measured relative position ``p_target - p_observer`` in the shared heading frame.

    Produced by the detection-association stage from two robots' detections of one object;
    consumed by the localizer like any other measurement.
    """

    t: float
    observer: str
    target: str
    vector: tuple[float, ...]
    """``p_target - p_observer`` (m), one entry per dimension: ``(dx, dy)`` in 2D."""
    sigma: float
    """Std (m) per axis."""


@dataclass(frozen=True, slots=True)
class SightingEvent:
    """``observer`` sees ``target`` at ``range`` (m) and ``bearing`` (rad, in ``(-pi, pi]``,
    counter-clockwise from the observer's forward axis): both, or one of them (the other
    ``None``). ``sigma_range`` and ``sigma_bearing`` are the sensor's noise for this sighting;
    ``sensor`` names it (``camera``, ``uwb_aoa``), for counting and reports."""

    t: float
    observer: str
    target: str
    range: float | None
    bearing: float | None
    sigma_range: float = 0.1
    sigma_bearing: float = 0.01
    sensor: str = "camera"


Event = (
    OdometryEvent
    | RangeEvent
    | DetectionEvent
    | GroundTruthEvent
    | HeightEvent
    | RelativeObservation
    | SightingEvent
)


class WakeRule(NamedTuple):
    """Which events a consumer must process at once, and which can wait: an event stamped
    ``t`` is *urgent* if it is a measurement with ``t >= measurement_from``, odometry with
    ``t >= odometry_from``, or if ``t`` is outside ``[lo, hi]``. An event that is not urgent
    cannot make an estimate now: processed later, in its order, it gives the same estimates
    (:meth:`relloc.localizers.base.Localizer.wake_rule`). A live source uses it to wake its
    engine thread only when it has to (:class:`relloc.sources.zenoh_source.ZenohSource`)."""

    measurement_from: float
    odometry_from: float
    lo: float
    hi: float

    def urgent(self, t: float, odometry: bool) -> bool:
        return not self.lo <= t <= self.hi or t >= (
            self.odometry_from if odometry else self.measurement_from
        )

    @staticmethod
    def combine(rules: Iterable[WakeRule]) -> WakeRule:
        """The rule of several consumers: an event is urgent if it is for any of ``rules``."""
        r = list(rules)
        return WakeRule(
            min(x.measurement_from for x in r), min(x.odometry_from for x in r),
            max(x.lo for x in r), min(x.hi for x in r),
        )  # fmt: skip


WAKE_ALWAYS = WakeRule(-math.inf, -math.inf, math.inf, -math.inf)
"""Every event is urgent."""


def measured_by(event: object, robot: str) -> bool:
    """Whether ``event`` comes from ``robot``'s own sensors, as its drivers publish it on board:
    its odometry, detections and height, the ranges its node measures (``robot_a``, the end that
    initiates a two-way range) and its sightings. Never ground truth."""
    if isinstance(event, RangeEvent):
        return event.robot_a == robot
    if isinstance(event, SightingEvent):
        return event.observer == robot
    if isinstance(event, (OdometryEvent, DetectionEvent, HeightEvent)):
        return event.robot == robot
    return False


def pair_key(a: str, b: str) -> str:
    """Order-independent key for a pair of names: ``pair_key("n_7", "n_3") == "n_3-n_7"``."""
    lo, hi = sorted((a, b))
    return f"{lo}-{hi}"
