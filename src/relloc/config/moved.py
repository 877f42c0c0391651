"""What became of the filter keys of earlier versions: moved to their sensor's section, or no
longer a setting (a documented constant of the module that uses it). A config or a
``with_filter`` call that names one is a :class:`~relloc.config.checks.ConfigError` whose
message names the change, never a silent default nor a bare "unknown key"."""

from __future__ import annotations

from typing import Any


def _constant(path: str, value: str) -> str:
    return f"is no longer a setting: it is the constant {path} ({value})"


MOVED: dict[str, tuple[str, str]] = {
    # [filter]
    "update_period": ("", _constant("relloc.localizers.grid.UPDATE_PERIOD", "0.1 s")),
    "estimate_period": ("", _constant("relloc.localizers.base.ESTIMATE_PERIOD", "0.1 s")),
    "max_time_jump": ("", _constant("relloc.localizers.clock.MAX_TIME_JUMP", "5 s")),
    "mcmc_steps": ("", _constant("relloc.filter.annealing.MCMC_STEPS", "3")),
    "spread_rotations": (
        "",
        "is no longer a setting: the annealed start always spreads the particles over the formation's "
        "rotations and reflections (relloc.filter.annealing)",
    ),
    # [filter.likelihood]
    "sigma_uwb": ("likelihood", "moved to [uwb] sigma"),
    "los_sigma": ("likelihood", "moved to [uwb] los_sigma"),
    "nlos_fraction": ("likelihood", _constant("relloc.filter.ranges.NLOS_FRACTION", "0.1")),
    "nlos_sigma": ("likelihood", _constant("relloc.filter.ranges.NLOS_SIGMA", "0.3 m")),
    "gross_fraction": ("likelihood", _constant("relloc.filter.ranges.GROSS_FRACTION", "0.02")),
    "outlier_fraction": ("likelihood", _constant("relloc.filter.ranges.OUTLIER_FRACTION", "0.1")),
    "max_range": ("likelihood", _constant("relloc.filter.ranges.MAX_RANGE", "15 m")),
    # [filter.odometry]
    "odom_noise_per_m": ("odometry", _constant("relloc.filter.motion.NOISE_PER_M", "0.05 per m")),
    "odom_noise_per_rad": (
        "odometry",
        _constant("relloc.filter.motion.NOISE_PER_RAD", "0.02 m per rad"),
    ),
    "process_noise": (
        "odometry",
        _constant("relloc.filter.motion.PROCESS_NOISE", "0.03 m per sqrt(s)"),
    ),
    "max_odom_extrapolation": ("odometry", _constant("relloc.odometry.MAX_EXTRAPOLATION", "0.5 s")),
    "max_speed": ("odometry", _constant("relloc.localizers.tracks.MAX_SPEED", "1.5 m/s")),
    "max_yaw_rate": ("odometry", _constant("relloc.localizers.tracks.MAX_YAW_RATE", "4 rad/s")),
    # [filter.resampling]
    "resample": (
        "resampling",
        "is no longer a setting: the sampled filter resamples when the effective sample size "
        "falls below relloc.filter.base.ESS_THRESHOLD",
    ),
    "ess_threshold": ("resampling", _constant("relloc.filter.base.ESS_THRESHOLD", "0.5")),
    "reinject_fraction": ("resampling", _constant("relloc.filter.base.REINJECT_FRACTION", "0.01")),
    "rotation_kernel_max_spread": (
        "resampling",
        _constant("relloc.estimators.particle.filter.ROTATION_KERNEL_MAX_SPREAD", "0.25 rad"),
    ),
    # [filter.self_calibration]
    "bias_prior_sigma": (
        "self_calibration",
        _constant("relloc.localizers.priors.BIAS_PRIOR_SIGMA", "0.05 m"),
    ),
    "bias_prior_sigma_uncalibrated": (
        "self_calibration",
        _constant("relloc.localizers.priors.BIAS_PRIOR_SIGMA_UNCALIBRATED", "0.25 m"),
    ),
    "scale_prior_sigma": (
        "self_calibration",
        _constant("relloc.filter.calibration.CalibrationNoise.scale_prior_sigma", "0.15"),
    ),
    "scale_walk": (
        "self_calibration",
        _constant("relloc.filter.calibration.CalibrationNoise.scale_walk", "0.001"),
    ),
    # [filter.adaptive]
    "min_particles_no_kernel": (
        "adaptive",
        _constant("relloc.filter.adaptive.MIN_PARTICLES_NO_KERNEL", "5000"),
    ),
    "kld_epsilon": ("adaptive", _constant("relloc.filter.adaptive.KLD_EPSILON", "0.05")),
    "kld_quantile": ("adaptive", _constant("relloc.filter.adaptive.KLD_QUANTILE", "0.99")),
    "kld_bin": ("adaptive", _constant("relloc.filter.adaptive.KLD_BIN", "0.2 m")),
    "mc_tolerance_ordered": (
        "adaptive",
        "is no longer a setting: the ordered resampling it switched on was removed (mc_tolerance "
        "holds along every direction)",
    ),
    # [filter.association] -> [association]
    "sigma_det": ("association", "moved to [association] sigma_det"),
    "det_sigma_per_m": ("association", "moved to [association] det_sigma_per_m"),
    "det_heading_drift": ("association", "moved to [association] det_heading_drift"),
    "detection_window": ("association", "moved to [association] detection_window"),
    "d_th": ("association", "moved to [association] d_th"),
    "det_range_gate": ("association", "moved to [association] det_range_gate"),
    "det_range_max_age": (
        "association",
        _constant("relloc.stages.association.RANGE_MAX_AGE", "0.3 s"),
    ),
    "det_converged_std": (
        "association",
        _constant("relloc.stages.association.CONVERGED_STD", "0.5 m"),
    ),
    "det_gate_sigmas": ("association", _constant("relloc.stages.association.GATE_SIGMAS", "2")),
}
"""Old key -> (its section under ``[filter]``, ``""`` for the top; what became of it)."""


def moved_message(key: str) -> str | None:
    """What became of the old filter key ``key``, as a sentence naming its old place; ``None``
    if it is not one."""
    if key not in MOVED:
        return None
    section, what = MOVED[key]
    return f"[filter{'.' + section if section else ''}] {key} {what}"


def moved_key_error(section: str, key: str, value: Any) -> str | None:
    """The error for ``key`` read in ``[filter.<section>]`` (``section`` ``""``: the top of
    ``[filter]``, where the flat layout of earlier versions wrote every key) if it is an old
    one, else ``None``. The old ``[filter.association]`` table names the first key it holds."""
    if section == "" and key == "association":
        table = value if isinstance(value, dict) else {}
        for inner in table:
            if inner in MOVED and MOVED[inner][0] == "association":
                return moved_message(inner)
        return "[filter.association] moved to the [association] table"
    if key in MOVED and section in ("", MOVED[key][0]):
        return moved_message(key)
    return None


def association_key_error(key: str) -> str | None:
    """The error for ``key`` read in ``[association]`` if it became a constant, else ``None``."""
    if key in MOVED and MOVED[key][0] == "association" and not MOVED[key][1].startswith("moved"):
        return moved_message(key)
    return None
