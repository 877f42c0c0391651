"""The filter's section of a team config (``[filter]`` and its ``[filter.<section>]`` tables):
which filter runs (``kind``), how many particles, and what users vary of the sampled and the
self-calibrating filters. What nothing varies is a documented constant in the module that
uses it, and a sensor's noise lives with its sensor (:mod:`relloc.config.sensors`); a key that
moved or became a constant is a :class:`ConfigError` that says so (:mod:`relloc.config.moved`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal, get_args

from relloc.config.checks import Checked, ConfigError, build, require, type_hints
from relloc.config.moved import moved_key_error, moved_message

FilterKind = str
"""The filter a config names: a kind registered in :mod:`relloc.estimators` (``particle``,
``gaussian_sum``, ``range_graph``, ``smoother`` and any plug-in's), or ``auto``, the one the
registry picks for the team's modes and size (:func:`relloc.estimators.choose`). The registry
checks the name and what the kind can do when the run starts (:func:`relloc.estimators.check`)."""


@dataclass(frozen=True)
class LikelihoodConfig(Checked):
    """Measurement likelihoods of the filters (``[filter.likelihood]``): the range models of
    :mod:`relloc.filter.ranges` (their noise is the sensor's: ``[uwb] sigma`` and
    ``los_sigma``)."""

    range_model: Literal["nlos", "symmetric"] = "nlos"
    """Range likelihood of the particle filter (``relloc.filter.ranges``). ``nlos``: Gaussian
    line-of-sight noise ``[uwb] los_sigma``, a one-sided non-line-of-sight part (ranges too long
    by a half-normal excess) and a uniform floor; ``symmetric``: Gaussian ``[uwb] sigma`` plus a
    uniform part. The symmetric model is always used for ranges corrected by a learned model
    (the correction has predicted the skewed part), with online biases of uncalibrated pairs
    (an unknown bias and the one-sided excess are confounded; a calibrated prior pins the
    line-of-sight peak) and by the self-calibrating filter."""


@dataclass(frozen=True)
class OdometryConfig(Checked):
    """Motion (``[filter.odometry]``): the formation's heading drift and how an unheard robot's
    covariance grows (the odometry noise model itself is :mod:`relloc.filter.motion`'s)."""

    rotation_noise: float = 0.0
    """Random turn of the whole formation about the reference (rad per sqrt(s)): the drift of
    the shared heading (a model of the compass, unlike ``rotation_kernel``)."""
    unseen_speed: float = 0.25
    """How fast (m/s, one standard deviation per axis) a robot nothing is heard of may be
    moving: once its odometry is past its extrapolation (:data:`relloc.odometry.MAX_EXTRAPOLATION`)
    and it has had no range for 2 s, its published covariance grows by ``(unseen_speed *
    seconds unseen)^2`` (everyone's, when it is the reference), and the estimate lists it in
    ``unseen``. 0 turns it off."""

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self, "filter.odometry", non_negative=("rotation_noise", "unseen_speed"))


@dataclass(frozen=True)
class ResamplingConfig(Checked):
    """What follows a resampling of the sampled filter (``[filter.resampling]``; when it
    resamples and how much it re-draws from the prior are :mod:`relloc.filter.base`'s)."""

    rotation_kernel: float = 0.1
    """After each resampling, the fraction of the variance of the formation's orientation
    about the reference that is re-drawn by a Liu-West kernel (mean and variance kept): restores
    the diversity that resampling loses along the one direction ranges cannot see
    (``relloc.estimators.particle.filter``). Only for a formation (three robots or more). 0 disables it."""

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self, "filter.resampling", unit=("rotation_kernel",))


@dataclass(frozen=True)
class SelfCalibrationConfig(Checked):
    """What is estimated online and how (``[filter.self_calibration]``, docs/explanation/self-calibration.md).
    The defaults are the compass/fixed/calibrated modes."""

    heading_mode: Literal["compass", "estimate"] = "compass"
    """``compass``: each robot's odometry is rotated by its configured ``heading_offset_deg``
    into the shared frame; ``estimate``: the rotation of every robot's odometry frame relative
    to the reference robot's is estimated online (uniform prior) and the estimates are
    expressed in the reference robot's odometry frame (``heading_offset_deg`` is not read)."""
    odom_scale_mode: Literal["fixed", "online"] = "fixed"
    """``fixed``: odometry is multiplied by the configured ``odom_scale``; ``online``: every
    robot's odometry scale is estimated (prior
    :attr:`relloc.estimators.gaussian_sum.filter.CalibrationNoise.scale_prior_sigma` around 1; not read
    from the config)."""
    scale_min: float = 0.5
    """Online scale: the smallest physical odometry scale; below it the calibration restarts
    (:mod:`relloc.localizers.bounds`)."""
    scale_max: float = 1.5
    """Online scale: the largest physical odometry scale; above it the calibration restarts."""
    bias_mode: Literal["calibrated", "online"] = "calibrated"
    """``calibrated``: each pair's bias is the config's (or ``uwb.default_bias``);
    ``online``: every particle carries a Kalman belief about each pair's bias (Rao-Blackwellised),
    its prior the calibration when present, else around ``uwb.default_bias``
    (:mod:`relloc.estimators.particle.localizer`)."""
    bias_walk: float = 0.01
    """Online mode: random walk of each bias (m per sqrt(s)): orientation-dependent errors
    make the effective bias drift as the robots turn. The smoother holds each bias constant
    (a walk of re-keyed biases broke GTSAM's fixed-lag marginalisation)."""
    heading_walk: float = 0.01
    """Estimate mode: random walk of each relative heading (rad per sqrt(s)): gyro drift."""
    reference_heading_walk: float = 0.003
    """Estimate mode: random walk of the reference robot's own odometry heading (rad per
    sqrt(s)); its drift turns the frame it defines, and only its motion tells it."""
    gyro_bias_sigma: float = 0.0
    """Estimate mode: > 0 holds each robot's constant heading drift rate (its gyro bias) as a
    state with this prior standard deviation (rad/s), beside the heading's random walk; 0: the
    walk alone follows the drift, with a lag (docs/explanation/self-calibration.md)."""
    heading_split_std: float = 0.0
    """Estimate mode: split a Gaussian of the self-calibrating filter into three along a
    heading whose angular std has grown past this (rad; 0: never), keeping the count
    (relloc.estimators.gaussian_sum.filter, "Splitting a heading that has grown wide")."""
    heading_prior_sigma_deg: float = 0.0
    """Estimate mode: > 0 uses the configured heading offsets as a prior with this standard
    deviation (deg); 0 (default): uniform prior, the offsets are not read."""
    selfcal_particles: int = 1000
    """Particles (Gaussians) of the self-calibrating filter (heading estimate or online scale),
    each carrying a Kalman filter over positions and calibration (relloc.estimators.gaussian_sum.filter)."""
    selfcal_init_particles: int = 20000
    """Particles of the annealed start of the self-calibrating filter (then subsampled)."""
    selfcal_position_sigma: float = 0.2
    """Initial position standard deviation of each Gaussian after the annealed start (m)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self,
            "filter.self_calibration",
            at_least_one=("selfcal_particles", "selfcal_init_particles"),
            positive=("selfcal_position_sigma", "scale_min", "scale_max"),
            non_negative=(
                "bias_walk",
                "heading_walk",
                "reference_heading_walk",
                "gyro_bias_sigma",
                "heading_split_std",
                "heading_prior_sigma_deg",
            ),
        )


@dataclass(frozen=True)
class AdaptiveConfig(Checked):
    """The adaptive particle count of the sampled filter (``[filter.adaptive]``,
    :mod:`relloc.filter.adaptive`): ``particles`` (of ``[filter]``) at the start, after a
    divergence and while the posterior is wide (orientation unobservable, several modes); once
    it is one narrow mode, KLD-sampling's bound at each resampling, at least ``min_particles``."""

    particle_count: Literal["kld", "fixed"] = "kld"
    """``kld``: adapt the count; ``fixed``: always ``particles``."""
    min_particles: int = 2000
    """Fewest particles once the posterior is narrow (capped at ``particles``; where the
    orientation kernel cannot act, :data:`relloc.filter.adaptive.MIN_PARTICLES_NO_KERNEL`)."""
    mc_tolerance: float = 0.007
    """Monte Carlo standard error (m) allowed for the published position along the posterior's
    widest direction: at least ``sigma^2 / (ess_threshold mc_tolerance^2)`` particles; 0: no
    such floor."""

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self, "filter.adaptive", at_least_one=("min_particles",), non_negative=("mc_tolerance",)
        )


SECTIONS = ("likelihood", "odometry", "resampling", "self_calibration", "adaptive")
"""The sections of :class:`FilterConfig`, in file order."""


@dataclass(frozen=True)
class FilterConfig(Checked):
    """Filter parameters, in sections (``[filter.<section>]`` in a file); what every method
    shares is at the top. The defaults are the ones used on every shared recording."""

    kind: FilterKind = "auto"
    """Which filter runs as ``pf`` (:data:`FilterKind`); one that cannot do what the modes of
    ``[filter.self_calibration]`` ask is a :class:`ConfigError` when the run starts."""
    particles: int = 50000
    """Particles of the sampled filter: its full count, at the start and while the posterior is
    wide (``[filter.adaptive]`` lowers it once the posterior is narrow)."""
    init_window: float = 0.5
    """Collect ranges for this long before the first (annealed) update (s)."""
    likelihood: LikelihoodConfig = field(default_factory=LikelihoodConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    resampling: ResamplingConfig = field(default_factory=ResamplingConfig)
    self_calibration: SelfCalibrationConfig = field(default_factory=SelfCalibrationConfig)
    adaptive: AdaptiveConfig = field(default_factory=AdaptiveConfig)

    def __post_init__(self) -> None:
        """Reject values no filter can run with (a typo must not become a silent NaN). Whether
        the kind exists and can do what the modes ask is the registry's check
        (:func:`relloc.estimators.check`), when the run starts."""
        super().__post_init__()
        require(self, "filter", at_least_one=("particles",), non_negative=("init_window",))
        if not self.kind:
            raise ConfigError("filter.kind: expected a filter kind's name or 'auto'")

    @classmethod
    def sections(cls) -> dict[str, type]:
        """Section name -> its dataclass."""
        hints = type_hints(cls)  # type: ignore[arg-type]  # a class is hashable
        return {name: hints[name] for name in SECTIONS}

    @classmethod
    def section_of(cls, name: str) -> str | None:
        """The section holding the field ``name`` (``""``: the top of ``[filter]``; ``None``:
        no such field). Field names are unique across the sections."""
        if name in SECTIONS:
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
        return get_args(type_hints(owner)[name])

    def with_changes(self, **changes: Any) -> FilterConfig:
        """A copy with fields changed, each named by itself (its section is found: field names
        are unique), or whole sections replaced by their names. A name that moved or became a
        constant is a :class:`ConfigError` saying so; any other unknown name a ``TypeError``."""
        top: dict[str, Any] = {}
        nested: dict[str, dict[str, Any]] = {}
        for name, value in changes.items():
            section = "" if name in SECTIONS else self.section_of(name)
            if section is None:
                message = moved_message(name)
                if message is not None:
                    raise ConfigError(message)
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
        """``[filter]`` and its ``[filter.<section>]`` tables as read from a file. A key that
        moved or became a constant is a :class:`ConfigError` naming the change
        (:func:`relloc.config.moved.moved_key_error`); a key of a section written at the top of
        ``[filter]`` (the flat layout of earlier versions) one that names its place."""
        raw = dict(raw)
        for key, value in raw.items():
            error = moved_key_error("", key, value)
            if error is not None:
                raise ConfigError(error)
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
            for key in table:
                error = moved_key_error(section, key, table[key])
                if error is not None:
                    raise ConfigError(error)
            built[section] = build(sub, table, f"filter.{section}")
        return build(cls, {**raw, **built}, "filter")
