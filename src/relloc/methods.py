"""Named methods, as in the paper's results, built as engine pipelines.

=================  ==========================================================================
``pf``             particle filter, UWB ranges + odometry (the paper's PF_U)
``pf_ul``          ``pf`` with learned range-error correction in front (PF_UL)
``pf_uv``          ``pf`` with cooperative detections (association stage in front)
``pf_ulv``         both (PF_ULV)
``multilateration``  least squares on the ranges present (the paper's Multi)
``ekf_oracle``     the classical centralised cooperative-localization EKF over all poses
                   (Roumeliotis and Bekey), started at the ground truth: an oracle start
=================  ==========================================================================
"""

from __future__ import annotations

from pathlib import Path

from relloc import estimators
from relloc.config import TeamConfig
from relloc.engine import Pipeline, Stage
from relloc.localizers.base import Localizer

METHODS = ("pf", "pf_ul", "pf_uv", "pf_ulv", "multilateration", "ekf_oracle")

PARTICLE_METHODS: frozenset[str] = frozenset({"pf", "pf_ul", "pf_uv", "pf_ulv"})
"""Methods that run the filter ``[filter] kind`` names (:func:`filter_localizer`)."""

DETECTION_METHODS: frozenset[str] = frozenset({"pf_uv", "pf_ulv"})
"""Methods that fuse cooperative detections: only for them do sources read (and simulators
simulate) cameras and objects."""


class MethodError(ValueError):
    """A method name is unknown or its requirements (e.g. a models directory) are missing."""


PLANAR_METHODS: frozenset[str] = frozenset({"multilateration", "ekf_oracle"})
"""Methods that estimate in the plane only: a flying team (``dimension = 3``) cannot run them."""


def cannot_run(method: str, config: TeamConfig) -> str | None:
    """Why ``method`` cannot run for ``config``'s team (``None``: it can)."""
    if config.dimension == 3 and method in PLANAR_METHODS:
        return f"{method} estimates in 2D only; the team flies (dimension = 3)"
    return None


def parse_methods(text: str) -> list[str]:
    names = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in names if m not in METHODS]
    if unknown or not names:
        raise MethodError(
            f"unknown method(s) {unknown or text!r}; choose from {', '.join(METHODS)}"
        )
    return names


def build_pipeline(
    method: str,
    config: TeamConfig,
    *,
    seed: int = 0,
    models: Path | None = None,
    oracle_start: dict[str, tuple[float, float, float]] | None = None,
) -> Pipeline:
    """The pipeline (stages + localizer) of one named method. ``oracle_start``: every robot's
    true start pose (world frame), which only ``ekf_oracle`` takes."""
    if (why := cannot_run(method, config)) is not None:
        raise MethodError(why)
    if method == "ekf_oracle":
        if oracle_start is None:
            raise MethodError(
                "method ekf_oracle starts at the ground truth: the source has none to give it"
            )
        from relloc.localizers.ekf import EkfOracleLocalizer

        compass = config.with_modes(heading="compass", odom_scale="fixed")
        return Pipeline(method, EkfOracleLocalizer(compass, oracle_start))
    if method == "multilateration":
        from relloc.localizers.multilateration import MultilaterationLocalizer  # SciPy's optimiser

        return Pipeline(method, MultilaterationLocalizer(config, seed=seed))
    if method not in METHODS:
        raise MethodError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    stages: list[Stage] = []
    if method in ("pf_ul", "pf_ulv"):
        if models is None:
            raise MethodError(f"method {method} needs --models DIR (trained range-error models)")
        from relloc.stages.range_correction import RangeCorrector

        stages.append(RangeCorrector.from_config(config, models))
    if method in ("pf_uv", "pf_ulv"):
        from relloc.stages.association import DetectionAssociator

        stages.append(DetectionAssociator(config))
    return Pipeline(method, filter_localizer(config, seed=seed, method=method), stages)


def filter_choice(config: TeamConfig) -> tuple[str, str]:
    """The filter kind ``pf`` runs and why: the config's ``[filter] kind``, or for ``auto`` the
    one the registry picks for the team (:func:`relloc.estimators.choose`,
    docs/explanation/filter-kinds.md). A kind that cannot do what the modes ask is a
    :class:`relloc.config.ConfigError`."""
    kind, why = estimators.choose(config)
    return kind.name, why


def filter_kind(config: TeamConfig) -> str:
    """The filter ``pf`` runs (:func:`filter_choice`)."""
    return filter_choice(config)[0]


def filter_localizer(config: TeamConfig, *, seed: int = 0, method: str = "pf") -> Localizer:
    """The localizer of the kind :func:`filter_choice` names (its module imported now)."""
    kind, _ = estimators.choose(config)
    localizer: Localizer = kind.load()(config, seed=seed, method=method)
    return localizer


def filter_header(methods: list[str], config: TeamConfig) -> str | None:
    """The run header's line naming the filter the particle methods of ``methods`` run
    (``None`` if none of them does), e.g. ``filter: particle (kind "auto": 5 robots with odometry)``."""
    if not any(m in PARTICLE_METHODS for m in methods):
        return None
    kind, why = filter_choice(config)
    if config.filter.kind != "auto":
        return f'filter: {kind} (kind "{kind}")'
    return f'filter: {kind} (kind "auto": {why})'
