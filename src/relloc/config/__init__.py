"""Team configuration: robots, reference robot, prior area, sensors and filter parameters.

A team is described by one TOML file (see ``configs/``)::

    name = "multi4_shortbag_20221011"
    reference = "turtle04"
    area = [-4.0, 4.0, -4.5, 4.5]          # xmin, xmax, ymin, ymax of the arena (m)

    [[robots]]
    name = "turtle01"
    uwb_node = "n_7"
    odom_topic = "/cali/turtle01/odom"
    odom_mode = "twist"                   # integrate the twist ("twist") or use the pose ("pose")
    heading_offset_deg = 12.0             # odometry frame -> shared heading frame (the compass)
    odom_scale = 1.0
    mocap_body = "turtlebot1_cap"

    [uwb]
    default_bias = 0.3
    [uwb.pairs."n_3-n_7"]
    bias = 0.39

    [filter]
    particles = 20000
    [filter.likelihood]
    range_model = "nlos"

Everything has a default except the robots; unknown keys are errors (a typo must not silently
fall back to a default). ``TeamConfig.to_toml`` writes the file back, which is how
``relloc calibrate`` stores what it estimated.
"""

from __future__ import annotations

import functools
import math
import numbers
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from types import UnionType
from typing import Any, Literal, get_args, get_origin, get_type_hints

from relloc.events import RangeEvent, pair_key


class ConfigError(ValueError):
    """The team configuration is invalid; the message says which key and why."""


class _FieldError(ConfigError):
    """A field's value does not fit its annotation (:func:`_build` adds where it was read)."""


class _Checked:
    """Base of the config dataclasses: every field is checked against its annotation whenever
    one is made, from a file, by :func:`dataclasses.replace` or in code (:func:`_check_value`),
    so that a typo is a :class:`ConfigError` naming the key, never a silent default."""

    def __post_init__(self) -> None:
        hints = _type_hints(type(self))
        for f in fields(self):  # type: ignore[arg-type]
            _check_value(hints[f.name], getattr(self, f.name), f.name)


@dataclass(frozen=True)
class CameraConfig(_Checked):
    """Pose of the camera optical frame on the robot (x right, y down, z forward in the image).

    ``x, y, z`` is the optical centre in the robot body frame (m); ``yaw_deg`` and ``pitch_deg``
    turn a forward-looking, level camera (yaw left positive, pitch down positive).
    """

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    fov_deg: float = 70.0
    max_range: float = 5.0


@dataclass(frozen=True)
class RobotConfig(_Checked):
    """One robot of the team and where its data comes from."""

    name: str
    uwb_node: str = ""
    odom_topic: str = ""
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
    teammate in this robot's body frame (docs/mrclam.md, "Sightings over ROS 2")."""
    sighting_sigma_range: float = 0.1
    """Range noise of those sightings (m)."""
    sighting_sigma_bearing_deg: float = 1.0
    """Bearing noise of those sightings (deg)."""

    @property
    def heading_offset(self) -> float:
        """Heading offset in radians."""
        return math.radians(self.heading_offset_deg)


@dataclass(frozen=True)
class PairCalibration(_Checked):
    """Range calibration of one UWB transceiver pair: ``measured = scale * true + bias``."""

    bias: float = 0.0
    scale: float = 1.0
    sigma: float | None = None
    """Range noise for this pair; ``None`` uses the filter's ``sigma_uwb``."""
    source: str = ""
    """Which recording this calibration was estimated from."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.scale > 0.0:
            raise ConfigError(f"a pair's range scale must be > 0, got {self.scale}")
        if self.sigma is not None and not self.sigma > 0.0:
            raise ConfigError(f"a pair's sigma must be > 0, got {self.sigma}")


@dataclass(frozen=True)
class UwbConfig(_Checked):
    """UWB topics and per-transceiver-pair calibration."""

    range_topic: str = "/uwb/tof/{a}/{b}/distance"
    """Topic template; ``{a}`` and ``{b}`` are node ids."""
    default_bias: float = 0.3
    """Bias assumed for a pair with no calibration (m)."""
    default_bias_sigma: float = 0.15
    """Extra range noise for an uncalibrated pair (added in quadrature to ``sigma_uwb``)."""
    pairs: dict[str, PairCalibration] = field(default_factory=dict)

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
class LikelihoodConfig(_Checked):
    """Measurement likelihoods of the filters (``[filter.likelihood]``): the range models of
    :mod:`relloc.filter.ranges`."""

    range_model: Literal["nlos", "symmetric"] = "nlos"
    """Range likelihood of the particle filter (``relloc.filter.ranges``). ``nlos``: Gaussian
    line-of-sight noise ``los_sigma``, a one-sided non-line-of-sight part (ranges too long by a
    half-normal excess of scale ``nlos_sigma``, weight ``nlos_fraction``) and a uniform floor
    ``gross_fraction``; ``symmetric``: Gaussian ``sigma_uwb`` plus uniform ``outlier_fraction``.
    The symmetric model is always used for ranges corrected by a learned model (the correction
    has predicted the skewed part), with online biases (an unknown bias and the one-sided excess
    are confounded) and by the self-calibrating filter."""
    los_sigma: float = 0.1
    """NLOS-aware model: line-of-sight range noise (m), wider than the training residuals' for
    the pair biases moving between sessions (docs/results.md, "Design measurements behind the
    filter's defaults")."""
    nlos_fraction: float = 0.1
    """NLOS-aware model: weight of the non-line-of-sight part."""
    nlos_sigma: float = 0.3
    """NLOS-aware model: scale of the excess delay of a blocked path (m)."""
    gross_fraction: float = 0.02
    """NLOS-aware model: weight of the uniform part (gross errors of any sign)."""
    sigma_uwb: float = 0.15
    """Symmetric model: standard deviation of the Gaussian part of the range likelihood (m)."""
    outlier_fraction: float = 0.1
    """Symmetric model: weight of the uniform (NLOS/outlier) part of the range likelihood."""
    max_range: float = 15.0
    """Support of the uniform outlier density (m)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(
            self, "filter.likelihood", positive=("los_sigma", "nlos_sigma", "sigma_uwb", "max_range"),
            fraction=("nlos_fraction", "gross_fraction", "outlier_fraction"),
        )
        if self.nlos_fraction + self.gross_fraction >= 1.0:
            raise ConfigError(
                f"filter.likelihood.nlos_fraction + gross_fraction must be < 1, got {self.nlos_fraction} + "
                f"{self.gross_fraction}"
            )


@dataclass(frozen=True)
class OdometryConfig(_Checked):
    """Motion noise (``[filter.odometry]``): the one odometry noise model of both filters
    (:class:`relloc.filter.motion.OdometryMotion`) and how far odometry is extrapolated."""

    odom_noise_per_m: float = 0.05
    """Odometry displacement noise, standard deviation per metre travelled (fraction)."""
    odom_noise_per_rad: float = 0.02
    """Lateral noise per radian turned (m/rad), for heading errors during turns."""
    process_noise: float = 0.03
    """Random-walk noise of every relative position (m per sqrt(s)); keeps static robots alive."""
    rotation_noise: float = 0.0
    """Random turn of the whole formation about the reference (rad per sqrt(s)): the drift of
    the shared heading (a model of the compass, unlike ``rotation_kernel``)."""
    max_odom_extrapolation: float = 0.5
    """How far past a robot's last odometry message its motion is extrapolated (s)."""
    max_speed: float = 1.5
    """Fastest a robot's odometry may move it (m/s; ground robots): a faster step between two
    messages (beyond a 0.25 m jitter slack) is a reset or jump, and re-anchors that robot's
    odometry track instead of moving it (counted ``odometry_reanchored``)."""
    max_yaw_rate: float = 4.0
    """Fastest a robot's odometry may turn it (rad/s; 0.3 rad of slack), as ``max_speed``."""
    unseen_speed: float = 0.25
    """How fast (m/s, one standard deviation per axis) a robot nothing is heard of may be
    moving: once its odometry is past ``max_odom_extrapolation`` and it has had no range for
    2 s, its published covariance grows by ``(unseen_speed * seconds unseen)^2`` (everyone's,
    when it is the reference), and the estimate lists it in ``unseen``. 0 turns it off."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(self, "filter.odometry", non_negative=(
            "odom_noise_per_m", "odom_noise_per_rad", "process_noise", "rotation_noise", "max_odom_extrapolation",
            "unseen_speed",
        ), positive=("max_speed", "max_yaw_rate"))


@dataclass(frozen=True)
class ResamplingConfig(_Checked):
    """When and how the particles are resampled (``[filter.resampling]``), with the
    re-injection from the prior and the orientation kernel that follow a resampling."""

    resample: Literal["every_step", "ess"] = "ess"
    ess_threshold: float = 0.5
    """Resample when the effective sample size falls below this fraction of ``particles``."""
    reinject_fraction: float = 0.01
    """Fraction of particles re-drawn from the prior at each resampling (recovery)."""
    rotation_kernel: float = 0.1
    """After each resampling, the fraction of the variance of the formation's orientation
    about the reference that is re-drawn by a Liu-West kernel (mean and variance kept): restores
    the diversity that resampling loses along the one direction ranges cannot see
    (``relloc.filter.pf``). Only for a formation (three robots or more). 0 disables it."""
    rotation_kernel_max_spread: float = 0.25
    """The kernel acts only when the orientations form one mode with a robust standard
    deviation below this (rad), never while rotations or mirror images compete."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(
            self, "filter.resampling", non_negative=("rotation_kernel_max_spread",),
            fraction=("reinject_fraction",), unit=("ess_threshold", "rotation_kernel"),
        )


@dataclass(frozen=True)
class SelfCalibrationConfig(_Checked):
    """What is estimated online and how (``[filter.self_calibration]``, docs/self-calibration.md).
    The defaults are the compass/fixed/calibrated modes."""

    heading_mode: Literal["compass", "estimate"] = "compass"
    """``compass``: each robot's odometry is rotated by its configured ``heading_offset_deg``
    into the shared frame; ``estimate``: the rotation of every robot's odometry frame relative
    to the reference robot's is estimated online (uniform prior) and the estimates are
    expressed in the reference robot's odometry frame (``heading_offset_deg`` is not read)."""
    odom_scale_mode: Literal["fixed", "online"] = "fixed"
    """``fixed``: odometry is multiplied by the configured ``odom_scale``; ``online``: every
    robot's odometry scale is estimated (prior ``1 +- scale_prior_sigma``; not read from the
    config)."""
    bias_mode: Literal["calibrated", "online"] = "calibrated"
    """``calibrated``: each pair's bias is the config's (or ``uwb.default_bias``);
    ``online``: every particle carries a Kalman belief about each pair's bias (Rao-Blackwellised),
    its prior the calibration when present, else around ``uwb.default_bias``."""
    bias_prior_sigma: float = 0.05
    """Online mode: prior standard deviation of a calibrated pair's bias (m)."""
    bias_prior_sigma_uncalibrated: float = 0.25
    """Online mode, Gaussian-sum filter (headings or scales estimated as well): prior standard
    deviation of an uncalibrated pair's bias (m). The sampled filter (``--bias online`` alone)
    uses ``uwb.default_bias_sigma`` instead, the width its default mode assumes for the same
    pair: a wider prior let the bias run, on a new session, along what one range cannot tell
    apart (a longer bias, a nearer robot) (docs/self-calibration.md, "Online bias on a new
    session")."""
    bias_walk: float = 0.01
    """Online mode: random walk of each bias (m per sqrt(s)): orientation-dependent errors
    make the effective bias drift as the robots turn."""
    heading_walk: float = 0.01
    """Estimate mode: random walk of each relative heading (rad per sqrt(s)): gyro drift."""
    reference_heading_walk: float = 0.003
    """Estimate mode: random walk of the reference robot's own odometry heading (rad per
    sqrt(s)); its drift turns the frame it defines, and only its motion tells it."""
    heading_split_std: float = 0.0
    """Estimate mode: split a Gaussian of the self-calibrating filter into three along a
    heading whose angular std has grown past this (rad; 0: never), keeping the count
    (relloc.filter.gaussian_sum, "Splitting a heading that has grown wide")."""
    heading_prior_sigma_deg: float = 0.0
    """Estimate mode: > 0 uses the configured heading offsets as a prior with this standard
    deviation (deg); 0 (default): uniform prior, the offsets are not read."""
    scale_prior_sigma: float = 0.15
    """Online scale: prior standard deviation of each odometry scale around 1."""
    scale_walk: float = 0.001
    """Online scale: random walk of each odometry scale (per sqrt(s))."""
    selfcal_particles: int = 1000
    """Particles (Gaussians) of the self-calibrating filter (heading estimate or online scale),
    each carrying a Kalman filter over positions and calibration (relloc.filter.gaussian_sum)."""
    selfcal_init_particles: int = 20000
    """Particles of the annealed start of the self-calibrating filter (then subsampled)."""
    selfcal_position_sigma: float = 0.2
    """Initial position standard deviation of each Gaussian after the annealed start (m)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(
            self, "filter.self_calibration", at_least_one=("selfcal_particles", "selfcal_init_particles"),
            positive=("selfcal_position_sigma", "scale_prior_sigma"),
            non_negative=(
                "bias_prior_sigma", "bias_prior_sigma_uncalibrated", "bias_walk", "heading_walk",
                "reference_heading_walk", "heading_split_std", "heading_prior_sigma_deg", "scale_walk",
            ),
        )


@dataclass(frozen=True)
class AssociationConfig(_Checked):
    """Cooperative detections (``[filter.association]``; :mod:`relloc.stages.association`,
    methods ``pf_uv`` / ``pf_ulv``)."""

    sigma_det: float = 0.15
    """Standard deviation of a cooperative-detection relative position, per axis (m)."""
    detection_window: float = 0.1
    """Detections of two robots are paired when their capture times differ by at most this (s)."""
    d_th: float = 0.15
    """Association threshold: a detection pair must agree with the converged estimate within
    this (m), widened by the estimate's own uncertainty (``det_gate_sigmas``)."""
    det_sigma_per_m: float = 0.03
    """Relative-position noise growing with detection distance (m per m, per detection, added
    in quadrature to ``sigma_det``): stereo depth noise and heading error grow with range."""
    det_converged_std: float = 0.5
    """The estimate of a pair counts as converged (and gates detections) when both robots'
    position standard deviations are below this (m)."""
    det_gate_sigmas: float = 2.0
    """Widening of the estimate gate by the estimate's standard deviation (multiples)."""
    det_range_gate: float = 0.3
    """Before convergence: a pair's implied distance must match the pair's latest (bias-corrected)
    UWB range within this (m)."""
    det_range_max_age: float = 0.3
    """The UWB range used by the range gate must be at most this old (s)."""
    det_heading_drift: float = 0.003
    """Growth of a robot's odometry-heading uncertainty per second of motion (rad/s), which
    weakens its detection vectors over time."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(self, "filter.association", positive=("sigma_det",), non_negative=(
            "detection_window", "d_th", "det_sigma_per_m", "det_converged_std", "det_gate_sigmas", "det_range_gate",
            "det_range_max_age", "det_heading_drift",
        ))


@dataclass(frozen=True)
class AdaptiveConfig(_Checked):
    """The adaptive particle count of the sampled filter (``[filter.adaptive]``,
    :mod:`relloc.filter.adaptive`): ``particles`` (of ``[filter]``) at the start, after a
    divergence and while the posterior is wide (orientation unobservable, several modes); once
    it is one narrow mode, KLD-sampling's bound at each resampling, at least ``min_particles``."""

    particle_count: Literal["kld", "fixed"] = "kld"
    """``kld``: adapt the count; ``fixed``: always ``particles``."""
    min_particles: int = 2000
    """Fewest particles once the posterior is narrow (capped at ``particles``)."""
    min_particles_no_kernel: int = 5000
    """The same where the orientation kernel cannot act (one non-reference robot, or
    ``rotation_kernel = 0``): nothing but the count then keeps the diversity of the weakly
    observed bearing (capped at ``particles``)."""
    kld_epsilon: float = 0.05
    """KLD-sampling's bound on the Kullback-Leibler divergence of the binned sample."""
    kld_quantile: float = 0.99
    """Confidence ``1 - delta`` of that bound, in (0.5, 1)."""
    kld_bin: float = 0.2
    """Cell side (m) of the grid over the relative positions whose occupied cells are counted."""
    mc_tolerance: float = 0.007
    """Monte Carlo standard error (m) allowed for the published position along the posterior's
    widest direction: at least ``sigma^2 / (ess_threshold mc_tolerance^2)`` particles; 0: no
    such floor."""
    mc_tolerance_ordered: float = 0.0
    """The same along the principal axis of a formation's positions, along which an adaptive
    filter resamples in order (:mod:`relloc.filter.pf`: its mean drifts far less there per
    particle); the other directions keep ``mc_tolerance``. 0 (the default): no ordered
    resampling and ``mc_tolerance`` everywhere (the rule of session 5, draw for draw). 0.012
    gives the shortbag's 5x at its APE, but costs demo ``multi`` 0.005 m over seeds and the
    shortbag's silence test its bound (docs/adaptive-particles.md, "The shortbag's 5x")."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(self, "filter.adaptive", at_least_one=("min_particles", "min_particles_no_kernel"), positive=("kld_epsilon", "kld_bin"),
                 non_negative=("mc_tolerance", "mc_tolerance_ordered"))
        if not 0.5 < self.kld_quantile < 1.0:
            raise ConfigError(f"filter.adaptive.kld_quantile must be in (0.5, 1), got {self.kld_quantile}")


@dataclass(frozen=True)
class FilterConfig(_Checked):
    """Filter parameters, in sections (``[filter.<section>]`` in a file); what every method
    shares is at the top. The defaults are the ones used on every shared recording."""

    particles: int = 50000
    """Particles of the sampled filter: its full count, at the start and while the posterior is
    wide (``[filter.adaptive]`` lowers it once the posterior is narrow)."""
    update_period: float = 0.1
    """Measurements arriving within this window are fused in one update (s)."""
    estimate_period: float = 0.1
    """Estimates are emitted at this period (s)."""
    init_window: float = 0.5
    """Collect ranges for this long before the first (annealed) update (s)."""
    mcmc_steps: int = 3
    spread_rotations: bool = True
    """After the annealed start, spread particles over rotations/reflections about the reference
    (exact while only ranges have been seen); odometry motion then selects the right one."""
    max_time_jump: float = 5.0
    """The team clock's tolerance (s): an event stamped more than this after the newest
    accepted one (or before it, where it could no longer be used) is rejected (``time_jump``,
    ``time_jump_backward``) unless agreeing stamps from two sources outvote the events
    accepted meanwhile (:mod:`relloc.localizers.base`): one corrupted stamp, or one robot's
    wrong clock, must not drag the filter's clock away; a real step of the whole stream is
    followed after three events."""
    likelihood: LikelihoodConfig = field(default_factory=LikelihoodConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    resampling: ResamplingConfig = field(default_factory=ResamplingConfig)
    self_calibration: SelfCalibrationConfig = field(default_factory=SelfCalibrationConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    adaptive: AdaptiveConfig = field(default_factory=AdaptiveConfig)

    def __post_init__(self) -> None:
        """Reject values no filter can run with (a typo must not become a silent NaN)."""
        super().__post_init__()
        _require(
            self, "filter", at_least_one=("particles",), positive=("update_period", "estimate_period"),
            non_negative=("init_window", "mcmc_steps", "max_time_jump"),
        )

    @classmethod
    def sections(cls) -> dict[str, type]:
        """Section name -> its dataclass."""
        hints = _type_hints(cls)
        return {name: hints[name] for name in _SECTIONS}

    @classmethod
    def section_of(cls, name: str) -> str | None:
        """The section holding the field ``name`` (``""``: the top of ``[filter]``; ``None``:
        no such field). Field names are unique across the sections."""
        if name in _SECTIONS:
            return None
        if name in {f.name for f in fields(cls)}:
            return ""
        for section, sub in cls.sections().items():
            if name in {f.name for f in fields(sub)}:
                return section
        return None

    @classmethod
    def choices(cls, name: str) -> tuple[str, ...]:
        """The allowed values of the ``Literal`` field ``name`` of any section (e.g. for a CLI
        flag)."""
        section = cls.section_of(name)
        owner = cls.sections()[section] if section else cls
        return get_args(_type_hints(owner)[name])

    def with_changes(self, **changes: Any) -> FilterConfig:
        """A copy with fields changed, each named by itself (its section is found: field names
        are unique), or whole sections replaced by their names."""
        top: dict[str, Any] = {}
        nested: dict[str, dict[str, Any]] = {}
        for name, value in changes.items():
            section = "" if name in _SECTIONS else self.section_of(name)
            if section is None:
                raise TypeError(f"FilterConfig has no field {name!r}")
            if section:
                nested.setdefault(section, {})[name] = value
            else:
                top[name] = value
        for section, sub in nested.items():
            top[section] = replace(top.get(section, getattr(self, section)), **sub)
        return replace(self, **top)

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> FilterConfig:
        """``[filter]`` and its ``[filter.<section>]`` tables as read from a file. A key of a
        section written at the top of ``[filter]`` (the flat layout of earlier versions) is a
        :class:`ConfigError` that names its place."""
        raw = dict(raw)
        for key in raw:
            section = cls.section_of(key)
            if section:
                raise ConfigError(
                    f"filter.{key} has moved to the [filter.{section}] table: write {key} = ... under "
                    f"[filter.{section}]"
                )
        built: dict[str, Any] = {}
        for section, sub in cls.sections().items():
            table = raw.pop(section, {})
            if not isinstance(table, dict):
                raise ConfigError(f"filter.{section} must be a table ([filter.{section}])")
            built[section] = _build(sub, table, f"filter.{section}")
        return _build(cls, {**raw, **built}, "filter")


_SECTIONS = ("likelihood", "odometry", "resampling", "self_calibration", "association", "adaptive")
"""The sections of :class:`FilterConfig`, in file order."""


@dataclass(frozen=True)
class TeamConfig(_Checked):
    """Everything the engine needs to know about a team."""

    robots: tuple[RobotConfig, ...]
    reference: str
    name: str = "team"
    area: tuple[float, float, float, float] = (-4.0, 4.0, -4.5, 4.5)
    """Prior box of every robot's position: xmin, xmax, ymin, ymax (m)."""
    uwb: UwbConfig = field(default_factory=UwbConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    mocap_topic: str = "/vrpn_client_node/{body}/pose"
    clock_offset: float | None = None
    """Header stamp minus receive time (s) for topics with zero stamps; ``None``: estimate it."""
    ros_interface: Literal["bridge", "rmw_zenoh"] = "bridge"
    """How the robots are on Zenoh live: zenoh-bridge-ros2dds or rmw_zenoh (``--ros-interface``
    overrides it; see ``relloc.ros.interfaces``)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        names = [r.name for r in self.robots]
        if len(names) < 2:
            raise ConfigError("a team needs at least two robots")
        if len(set(names)) != len(names):
            raise ConfigError(f"robot names must be unique, got {names}")
        if self.reference not in names:
            raise ConfigError(f"reference robot {self.reference!r} is not one of {names}")
        xmin, xmax, ymin, ymax = self.area
        if not all(map(math.isfinite, self.area)) or not (xmin < xmax and ymin < ymax):
            raise ConfigError(f"area must be [xmin, xmax, ymin, ymax] with min < max: {self.area}")
        nodes = [r.uwb_node for r in self.robots if r.uwb_node]
        if len(set(nodes)) != len(nodes):
            raise ConfigError(f"each UWB node may be on one robot only: {nodes}")

    @property
    def robot_names(self) -> tuple[str, ...]:
        return tuple(r.name for r in self.robots)

    @property
    def others(self) -> tuple[str, ...]:
        """Non-reference robots, in config order: the order of the filter state."""
        return tuple(r.name for r in self.robots if r.name != self.reference)

    def robot(self, name: str) -> RobotConfig:
        for r in self.robots:
            if r.name == name:
                return r
        raise KeyError(f"unknown robot {name!r}; the team is {list(self.robot_names)}")

    def range_nodes(self, event: RangeEvent) -> tuple[str, str]:
        """The transceivers of a range: the event's node ids, else the robots' configured ones,
        else the robot names."""
        node_a = event.node_a or self.robot(event.robot_a).uwb_node or event.robot_a
        node_b = event.node_b or self.robot(event.robot_b).uwb_node or event.robot_b
        return node_a, node_b

    def robot_of_node(self, node: str) -> str | None:
        for r in self.robots:
            if r.uwb_node == node:
                return r.name
        return None

    def with_filter(self, **changes: Any) -> TeamConfig:
        """A copy with some filter parameters changed (:meth:`FilterConfig.with_changes`: each
        named by itself, whichever section holds it)."""
        return replace(self, filter=self.filter.with_changes(**changes))

    def with_modes(
        self,
        *,
        heading: str | None = None,
        bias: str | None = None,
        odom_scale: str | None = None,
        reference: str | None = None,
    ) -> TeamConfig:
        """A copy with the self-calibration modes set (``None`` keeps the config's): ``heading``
        ``compass|estimate``, ``bias`` ``calibrated|online``, ``odom_scale`` ``fixed|online``;
        ``reference`` makes another robot the reference. A mode outside its ``Literal`` is a
        :class:`ConfigError` (from :class:`FilterConfig` itself)."""
        changes: dict[str, Any] = {}
        if heading is not None:
            changes["heading_mode"] = heading
        if bias is not None:
            changes["bias_mode"] = bias
        if odom_scale is not None:
            changes["odom_scale_mode"] = odom_scale
        config = self.with_filter(**changes) if changes else self
        if reference is not None and reference != config.reference:
            if reference not in config.robot_names:
                raise ConfigError(f"reference {reference!r} is not one of {list(config.robot_names)}")
            config = replace(config, reference=reference)
        return config

    def with_robot(self, name: str, **changes: Any) -> TeamConfig:
        """A copy with one robot's settings changed."""
        robots = tuple(replace(r, **changes) if r.name == name else r for r in self.robots)
        return replace(self, robots=robots)

    # ------------------------------------------------------------------ (de)serialisation
    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TeamConfig:
        data = dict(data)
        try:
            robots_raw = data.pop("robots")
        except KeyError:
            raise ConfigError("the config has no [[robots]]") from None
        robots = []
        for i, raw in enumerate(robots_raw):
            raw = dict(raw)
            camera = _build(CameraConfig, raw.pop("camera", {}), f"robots[{i}].camera")
            robots.append(_build(RobotConfig, {**raw, "camera": camera}, f"robots[{i}]"))
        uwb_raw = dict(data.pop("uwb", {}))
        pairs = {
            pair_key(*_split_pair(k)): _build(PairCalibration, v, f"uwb.pairs.{k}")
            for k, v in uwb_raw.pop("pairs", {}).items()
        }
        uwb = _build(UwbConfig, {**uwb_raw, "pairs": pairs}, "uwb")
        flt = FilterConfig.from_dict(data.pop("filter", {}))
        if "area" in data:
            area = data["area"]
            numbers_only = isinstance(area, list | tuple) and all(
                isinstance(v, numbers.Real) and not isinstance(v, bool) for v in area
            )
            if not numbers_only or len(area) != 4:
                raise ConfigError(f"area must be four numbers [xmin, xmax, ymin, ymax], got {area!r}")
            data["area"] = tuple(float(v) for v in area)
        return _build(cls, {**data, "robots": tuple(robots), "uwb": uwb, "filter": flt}, "team")

    @classmethod
    def load(cls, path: str | Path) -> TeamConfig:
        path = Path(path)
        try:
            with path.open("rb") as fh:
                data = tomllib.load(fh)
        except FileNotFoundError:
            raise ConfigError(f"config file not found: {path}") from None
        except OSError as exc:
            raise ConfigError(f"cannot read config {path}: {exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML: {exc}") from None
        try:
            return cls.from_dict(data)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
        except (TypeError, ValueError, AttributeError) as exc:  # a table where a value belongs, ...
            raise ConfigError(f"{path}: malformed config ({type(exc).__name__}: {exc})") from None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["area"] = list(self.area)
        d["robots"] = [asdict(r) for r in self.robots]
        d["uwb"]["pairs"] = {k: _drop_none(asdict(v)) for k, v in self.uwb.pairs.items()}
        return _drop_none(d)

    def to_toml(self) -> str:
        return _dump_toml(self.to_dict())

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_toml())


# ---------------------------------------------------------------------------- helpers
def with_numeric_overrides(obj: Any, overrides: dict[str, Any], where: str) -> Any:
    """A copy of the dataclass ``obj`` with some numeric fields changed, as read from a file's
    table named ``where``: unknown keys and non-numbers are :class:`ConfigError`."""
    _check_known(type(obj), overrides, where)
    for key, value in overrides.items():
        _check_value(float, value, f"{where}.{key}")
    return replace(obj, **{k: float(v) for k, v in overrides.items()})


def _require(
    obj: Any,
    where: str,
    *,
    at_least_one: tuple[str, ...] = (),
    positive: tuple[str, ...] = (),
    non_negative: tuple[str, ...] = (),
    fraction: tuple[str, ...] = (),
    unit: tuple[str, ...] = (),
) -> None:
    """Range checks of numeric fields of ``obj`` (a table named ``where``): counts >= 1, values
    > 0 or >= 0, fractions in [0, 1) and in [0, 1]."""
    for name in at_least_one:
        if getattr(obj, name) < 1:
            raise ConfigError(f"{where}.{name} must be >= 1, got {getattr(obj, name)}")
    for name in positive:
        if not getattr(obj, name) > 0.0:
            raise ConfigError(f"{where}.{name} must be > 0, got {getattr(obj, name)}")
    for name in non_negative:
        if not getattr(obj, name) >= 0.0:
            raise ConfigError(f"{where}.{name} must be >= 0, got {getattr(obj, name)}")
    for name in fraction:
        if not 0.0 <= getattr(obj, name) < 1.0:
            raise ConfigError(f"{where}.{name} must be in [0, 1), got {getattr(obj, name)}")
    for name in unit:
        if not 0.0 <= getattr(obj, name) <= 1.0:
            raise ConfigError(f"{where}.{name} must be in [0, 1], got {getattr(obj, name)}")


def _check_known(cls: type, raw: dict[str, Any], where: str) -> None:
    known = {f.name for f in fields(cls)}
    unknown = set(raw) - known
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; known: {sorted(known)}")


def _build(cls: type, raw: dict[str, Any], where: str) -> Any:
    """``cls(**raw)`` from a file's table named ``where``: unknown keys and values that do not
    fit their annotations are a :class:`ConfigError` naming the key."""
    _check_known(cls, raw, where)
    try:
        return cls(**raw)
    except _FieldError as exc:
        raise ConfigError(f"{where}.{exc}") from None
    except TypeError as exc:
        raise ConfigError(f"{where}: {exc}") from None


@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
    return get_type_hints(cls)


def _check_value(hint: Any, value: Any, where: str) -> None:
    """``value`` fits ``hint``: numbers finite (not booleans), integers integral, booleans
    real booleans, strings strings, ``Literal`` choices spelled right; other hints unchecked."""
    if hint is bool and not isinstance(value, bool):
        raise _FieldError(f"{where}: expected true or false, got {value!r}")
    numeric = hint in (float, int) or (
        get_origin(hint) is UnionType and float in get_args(hint) and value is not None
    )
    if numeric and (isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value)):
        raise _FieldError(f"{where}: expected a finite number, got {value!r}")
    if hint is int and not isinstance(value, numbers.Integral):
        raise _FieldError(f"{where}: expected an integer, got {value!r}")
    if hint is str and not isinstance(value, str):
        raise _FieldError(f"{where}: expected a string, got {value!r}")
    if get_origin(hint) is Literal and value not in get_args(hint):
        raise _FieldError(f"{where}: expected one of {list(get_args(hint))}, got {value!r}")


def _split_pair(key: str) -> tuple[str, str]:
    parts = key.split("-")
    if len(parts) != 2 or not all(parts):
        raise ConfigError(f"uwb.pairs key {key!r} must look like 'n_3-n_7'")
    return parts[0], parts[1]


def _drop_none(d: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if v is None:
            continue
        out[k] = _drop_none(v) if isinstance(v, dict) else v
    return out


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} to TOML")


def _dump_toml(d: dict[str, Any]) -> str:
    lines: list[str] = []
    scalars = {k: v for k, v in d.items() if not isinstance(v, dict) and k != "robots"}
    for k, v in scalars.items():
        lines.append(f"{k} = {_toml_value(v)}")

    def table(prefix: str, t: dict[str, Any]) -> None:
        lines.append("")
        lines.append(f"[{prefix}]")
        subtables = {}
        for k, v in t.items():
            if isinstance(v, dict):
                subtables[k] = v
            else:
                lines.append(f"{k} = {_toml_value(v)}")
        for k, v in subtables.items():
            key = f'"{k}"' if "-" in k or "." in k else k
            table(f"{prefix}.{key}", v)

    for robot in d.get("robots", []):
        lines.append("")
        lines.append("[[robots]]")
        camera = robot.get("camera", {})
        for k, v in robot.items():
            if k != "camera":
                lines.append(f"{k} = {_toml_value(v)}")
        lines.append("[robots.camera]")
        for k, v in camera.items():
            lines.append(f"{k} = {_toml_value(v)}")
    for k, v in d.items():
        if isinstance(v, dict):
            table(k, v)
    return "\n".join(lines) + "\n"
