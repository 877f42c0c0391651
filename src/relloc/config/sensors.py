"""The sensors' sections of a team config: each robot (odometry, camera, sightings), the UWB
transceivers (topics, per-pair calibration, range noise) and the cooperative detections
(noise and association gates). A sensor's noise lives here, with the sensor, not under
``[filter]``."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Literal

from relloc.config.checks import Checked, ConfigError, require
from relloc.events import pair_key


@dataclass(frozen=True)
class CameraConfig(Checked):
    """Pose of the camera optical frame on the robot (x right, y down, z forward in the image).

    ``x, y, z`` is the optical centre in the robot body frame (m); ``yaw_deg`` and ``pitch_deg``
    turn a forward-looking, level camera (yaw left positive, pitch down positive).
    """

    x: float = 0.0
    """The optical centre's ``x`` in the robot body frame (m)."""
    y: float = 0.0
    """The optical centre's ``y`` in the robot body frame (m)."""
    z: float = 0.0
    """The optical centre's ``z`` in the robot body frame (m)."""
    yaw_deg: float = 0.0
    """Turn of the camera, left positive (deg)."""
    pitch_deg: float = 0.0
    """Tilt of the camera, down positive (deg)."""
    fov_deg: float = 70.0
    """Horizontal field of view (deg)."""
    max_range: float = 5.0
    """Farthest detection the camera reports (m)."""


@dataclass(frozen=True)
class TagConfig(Checked):
    """One UWB tag a robot carries: its node id and where it sits in the robot's body frame."""

    node: str
    lever_arm: tuple[float, ...] = (0.0, 0.0)
    """The tag's position in the robot's body frame (m; x forward, y left, z up if given)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        arm = tuple(self.lever_arm)
        if not self.node:
            raise ConfigError("a tag needs a node id")
        if len(arm) not in (2, 3) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in arm
        ):
            raise ConfigError(
                f"tag {self.node}: lever_arm must be [x, y] or [x, y, z] in metres, got {arm!r}"
            )
        object.__setattr__(self, "lever_arm", tuple(float(v) for v in arm))


_QUIET_DEFAULTS = frozenset({"height_topic", "height_offset", "height_sigma"})
"""Robot keys :meth:`RobotConfig.to_dict` writes only where they differ from the default."""


@dataclass(frozen=True)
class RobotConfig(Checked):
    """One robot of the team and where its data comes from."""

    name: str
    uwb_node: str = ""
    """The robot's one UWB tag, at its body origin (``tags`` for several, or off the origin)."""
    tags: tuple[TagConfig, ...] = ()
    """The robot's UWB tags with their lever arms; with two or more, ranges see its heading
    (docs/explanation/tags.md). Give ``uwb_node`` or ``tags``, not both."""
    odom_topic: str = ""
    """Where the robot's odometry comes from (``nav_msgs/Odometry``); empty: the robot has none
    (a drone, a tag, a UWB-only team) and the filters give it a motion prior instead. The
    simulator and the MRCLAM reader fill it for the robots whose odometry they supply."""
    odom_mode: Literal["pose", "twist"] = "pose"
    heading_offset_deg: float = 0.0
    """Rotation from this robot's odometry frame to the shared heading frame (the compass)."""
    odom_scale: float = 1.0
    """Multiplies odometry displacements (wheel-scale calibration)."""
    odom_zero_stamps: bool = False
    """The odometry topic has all-zero header stamps: use receive time minus the clock offset."""
    mocap_body: str = ""
    detection_topic: str = ""
    detection_format: Literal["depthai", "posearray", ""] = ""
    camera: CameraConfig = field(default_factory=CameraConfig)
    zenoh_scope: str = ""
    """Optional key prefix for this robot's topics in Zenoh (e.g. ``tb1``)."""
    cmd_vel_topic: str = ""
    sighting_topic: str = ""
    """Teammates this robot sees (a camera reading markers, UWB angle of arrival): a topic
    template with ``{target}`` (the teammate's name), ``geometry_msgs/PointStamped`` of the
    teammate in this robot's body frame (docs/explanation/mrclam.md, "Sightings over ROS 2")."""
    sighting_sigma_range: float = 0.1
    """Range noise of those sightings (m)."""
    sighting_sigma_bearing_deg: float = 1.0
    """Bearing noise of those sightings (deg)."""
    height_topic: str = ""
    """A downward range finder (``sensor_msgs/msg/Range``): the robot's height above the ground
    (a flying robot; :mod:`relloc.sensors.height`). Empty: none."""
    height_offset: float = 0.0
    """Added to the range finder's reading to give the body origin's height (m): the origin's
    height above the sensor, positive for a sensor mounted below the origin."""
    height_sigma: float = 0.03
    """Noise of those heights (m)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        tags = tuple(self.tags)
        if tags and self.uwb_node:
            raise ConfigError(
                f"robot {self.name}: give uwb_node (one tag at the body origin) or tags, not both"
            )
        if not all(isinstance(t, TagConfig) for t in tags):
            raise ConfigError(f"robot {self.name}: tags must be tables of node and lever_arm")
        nodes = [t.node for t in tags]
        if len(set(nodes)) != len(nodes):
            raise ConfigError(f"robot {self.name}: a node is listed twice in its tags: {nodes}")
        object.__setattr__(self, "tags", tags)
        if not self.height_sigma > 0.0:
            raise ConfigError(
                f"robot {self.name}: height_sigma must be > 0, got {self.height_sigma}"
            )

    def to_dict(self) -> dict[str, Any]:
        """The robot as a table of the config file. The height sensor's keys are left out at
        their defaults, so a robot without one is written as before it existed."""
        d = asdict(self)
        for f in fields(self):
            if f.name in _QUIET_DEFAULTS and d[f.name] == f.default:
                del d[f.name]
        return d

    @property
    def heading_offset(self) -> float:
        """Heading offset in radians."""
        return math.radians(self.heading_offset_deg)

    @property
    def tag_list(self) -> tuple[TagConfig, ...]:
        """The robot's tags: ``tags``, or ``uwb_node`` at the body origin, or none."""
        if self.tags:
            return self.tags
        return (TagConfig(self.uwb_node),) if self.uwb_node else ()

    @property
    def nodes(self) -> tuple[str, ...]:
        """The node ids of the robot's tags."""
        return tuple(t.node for t in self.tag_list)


@dataclass(frozen=True)
class PairCalibration(Checked):
    """Range calibration of one UWB transceiver pair: ``measured = scale * true + bias``."""

    bias: float = 0.0
    """Range bias of the pair (m)."""
    scale: float = 1.0
    """Range scale of the pair (dimensionless)."""
    sigma: float | None = None
    """Range noise for this pair (m); ``None`` uses ``[uwb] sigma`` (``los_sigma`` for the
    NLOS-aware likelihood)."""
    bias_sigma: float | None = None
    """Std (m) of the calibrated bias as a prior of the online biases (``bias_mode =
    "online"``: a calibration is a prior, still estimated); ``None``: ``BIAS_PRIOR_SIGMA`` of
    :mod:`relloc.localizers.priors`, the spread of a pair's bias between sessions."""
    source: str = ""
    """Which recording this calibration was estimated from."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.scale > 0.0:
            raise ConfigError(f"a pair's range scale must be > 0, got {self.scale}")
        if self.sigma is not None and not self.sigma > 0.0:
            raise ConfigError(f"a pair's sigma must be > 0, got {self.sigma}")
        if self.bias_sigma is not None and not self.bias_sigma > 0.0:
            raise ConfigError(f"a pair's bias_sigma must be > 0, got {self.bias_sigma}")


@dataclass(frozen=True)
class UwbConfig(Checked):
    """UWB topics and per-transceiver-pair calibration."""

    range_topic: str = "/uwb/tof/{a}/{b}/distance"
    """Topic template; ``{a}`` and ``{b}`` are node ids. With ``peer_field`` (one message per
    node listing its peers) ``{a}`` is the publishing node's id, or ``{robot}`` its robot."""
    range_type: str = "sensor_msgs/msg/Range"
    """Message type of the range topics: ``sensor_msgs/msg/Range`` or a UWB driver's own
    (``nlink_parser/msg/LinktrackNodeframe2``), defined in ``msg_dirs``."""
    distance_field: str = "range"
    """Field path of the distance (m): ``range``, or ``nodes[].dis`` in a sequence of peers."""
    peer_field: str = ""
    """Field path of a peer's node id in a type listing peers (``nodes[].id``); empty: one
    range per message, the topic names the pair."""
    msg_dirs: tuple[str, ...] = ()
    """Folders of ``.msg`` files (``<package>/msg/<Type>.msg``) defining ``range_type``;
    relative to the config file."""
    default_bias: float = 0.3
    """Bias assumed for a pair with no calibration (m)."""
    default_bias_sigma: float = 0.15
    """Extra range noise for an uncalibrated pair (m; added in quadrature to ``sigma`` or
    ``los_sigma``); with online biases, the std of an uncalibrated pair's own deviation from
    the team offset."""
    team_offset_sigma: float = 0.3
    """Online biases: std (m) of the offset every uncalibrated pair of the team shares about
    ``default_bias`` (one hardware delay). Broad: ``default_bias`` is one lab's hardware, and
    the team's ranges teach the offset (:class:`relloc.localizers.priors.BiasPrior`)."""
    node_offset_sigma: float = 0.05
    """Online biases: std (m) of each transceiver's own offset, shared by every pair it is in,
    calibrated or not (an antenna delay, what moves when the node turns or moves); 0: none."""
    sigma: float = 0.15
    """Range noise (m, one standard deviation) of the symmetric range likelihood (Gaussian plus
    uniform outliers, :mod:`relloc.filter.ranges`): ranges corrected by a learned model, pairs
    whose bias is estimated online, the self-calibrating filter and ``range_model =
    "symmetric"``."""
    los_sigma: float = 0.1
    """Line-of-sight range noise (m) of the NLOS-aware likelihood (``range_model = "nlos"``,
    the default for raw ranges), wider than the training residuals' for the pair biases moving
    between sessions (docs/explanation/measurements.md, "Design measurements behind the filter's defaults")."""
    range_delay: float = 0.0
    """How long a range's stamp lags the geometry it measures (s): half the window of a
    driver that averages its ranges (a LinkTrack set to 1 s averaging: 0.5), plus its latency.
    The 3D smoother places each range at its stamp minus this; the planar kinds, whose robots
    move a few cm in that time, read the stamp. ``relloc init`` measures it against motion
    capture (:func:`relloc.drafting.delay.range_delay`)."""
    pairs: dict[str, PairCalibration] = field(default_factory=dict)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self,
            "uwb",
            positive=("sigma", "los_sigma"),
            non_negative=(
                "default_bias_sigma",
                "team_offset_sigma",
                "node_offset_sigma",
                "range_delay",
            ),
        )
        dirs = self.msg_dirs
        if isinstance(dirs, str) or not all(isinstance(d, str) for d in dirs):
            raise ConfigError(f"uwb.msg_dirs must be a list of folders, got {dirs!r}")
        object.__setattr__(self, "msg_dirs", tuple(dirs))

    def calibration(self, node_a: str, node_b: str) -> tuple[float, float, float | None]:
        """(bias, scale, extra_sigma or per-pair sigma) for a node pair.

        Returns ``(bias, scale, sigma)`` where ``sigma`` is the pair's own noise if calibrated
        with one, or ``None``; the caller adds ``default_bias_sigma`` for uncalibrated pairs via
        :meth:`is_calibrated`.
        """
        cal = self.pairs.get(pair_key(node_a, node_b))
        if cal is None:
            return self.default_bias, 1.0, None
        return cal.bias, cal.scale, cal.sigma

    def is_calibrated(self, node_a: str, node_b: str) -> bool:
        return pair_key(node_a, node_b) in self.pairs


@dataclass(frozen=True)
class AssociationConfig(Checked):
    """Cooperative detections (``[association]``; :mod:`relloc.stages.association`, methods
    ``pf_uv`` / ``pf_ulv``): the detections' noise and the gates that pair them."""

    sigma_det: float = 0.15
    """Standard deviation of a cooperative-detection relative position, per axis (m)."""
    detection_window: float = 0.1
    """Detections of two robots are paired when their capture times differ by at most this (s)."""
    d_th: float = 0.15
    """Association threshold: a detection pair must agree with the converged estimate within
    this (m), widened by the estimate's own uncertainty
    (:data:`relloc.stages.association.GATE_SIGMAS`)."""
    det_sigma_per_m: float = 0.03
    """Relative-position noise growing with detection distance (m per m, per detection, added
    in quadrature to ``sigma_det``): stereo depth noise and heading error grow with range."""
    det_range_gate: float = 0.3
    """Before convergence: a pair's implied distance must match the pair's latest (bias-corrected)
    UWB range within this (m)."""
    det_heading_drift: float = 0.003
    """Growth of a robot's odometry-heading uncertainty per second of motion (rad/s), which
    weakens its detection vectors over time."""

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self,
            "association",
            positive=("sigma_det",),
            non_negative=(
                "detection_window",
                "d_th",
                "det_sigma_per_m",
                "det_range_gate",
                "det_heading_drift",
            ),
        )
