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

import importlib
from pathlib import Path

from relloc.config import TeamConfig
from relloc.engine import Pipeline, Stage
from relloc.localizers.filtered import FilterLocalizer
from relloc.localizers.range_graph import large_compass_team

METHODS = ("pf", "pf_ul", "pf_uv", "pf_ulv", "multilateration", "ekf_oracle")

PARTICLE_METHODS: frozenset[str] = frozenset({"pf", "pf_ul", "pf_uv", "pf_ulv"})
"""Methods that run the filter ``[filter] kind`` names (:func:`filter_localizer`)."""

DETECTION_METHODS: frozenset[str] = frozenset({"pf_uv", "pf_ulv"})
"""Methods that fuse cooperative detections: only for them do sources read (and simulators
simulate) cameras and objects."""


class MethodError(ValueError):
    """A method name is unknown or its requirements (e.g. a models directory) are missing."""


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


LOCALIZERS: dict[str, tuple[str, str]] = {
    "particle": ("relloc.localizers.sampled", "ParticleFilterLocalizer"),
    "gaussian_sum": ("relloc.localizers.self_calibrating", "SelfCalibratingLocalizer"),
    "range_graph": ("relloc.localizers.range_graph", "RangeGraphLocalizer"),
    "smoother": ("relloc.localizers.smoother", "SmootherLocalizer"),
}
"""The localizer of each filter kind of ``[filter] kind`` (:data:`relloc.config.FilterKind`), as
module and class: imported when chosen, so a process that runs the particle filter does not
carry GTSAM (the smoother) in its memory."""


def filter_choice(config: TeamConfig) -> tuple[str, str]:
    """The filter ``pf`` runs and why: the config's ``[filter] kind``, or for ``auto`` the one
    the team's measurements call for (docs/explanation/filter-kinds.md), in this order:

    * headings or odometry scales estimated: the self-calibrating Gaussian sum, the only kind
      that estimates them;
    * some robot without odometry (no ``odom_topic``): the smoother, which gives it a motion
      prior and lets later ranges correct where it was (online biases included: a key per
      node pair);
    * a large team in the shared heading frame with calibrated biases: the smoother too, whose
      window of native factors costs far less than particles and beats the range graph's
      Gaussian sum there (docs/scaling.md);
    * else the sampled particle filter (which estimates range biases itself with
      ``bias_mode = "online"``).

    A kind that cannot do what the modes ask is refused by the config itself
    (:class:`relloc.config.FilterConfig`)."""
    fc = config.filter
    if fc.kind != "auto":
        return fc.kind, "the config's"
    sc = fc.self_calibration
    if sc.heading_mode == "estimate":
        return "gaussian_sum", "headings estimated"
    if sc.odom_scale_mode == "online":
        return "gaussian_sum", "odometry scales estimated"
    n = len(config.robots)
    without = [r.name for r in config.robots if not r.odom_topic]
    if without:
        who = f"{len(without)} of {n} robots without odometry"
        if sc.bias_mode == "online":
            return "smoother", f"{who}, biases online"
        return "smoother", who
    if large_compass_team(config):
        return "smoother", f"{n} robots, a large team"
    return "particle", f"{n} robots with odometry"


def filter_kind(config: TeamConfig) -> str:
    """The filter ``pf`` runs (:func:`filter_choice`)."""
    return filter_choice(config)[0]


def filter_localizer(config: TeamConfig, *, seed: int = 0, method: str = "pf") -> FilterLocalizer:
    """The localizer of the filter :func:`filter_kind` names."""
    module, name = LOCALIZERS[filter_kind(config)]
    cls: type[FilterLocalizer] = getattr(importlib.import_module(module), name)
    return cls(config, seed=seed, method=method)


def filter_header(methods: list[str], config: TeamConfig) -> str | None:
    """The run header's line naming the filter the particle methods of ``methods`` run
    (``None`` if none of them does), e.g. ``filter: particle (kind "auto": 5 robots with odometry)``."""
    if not any(m in PARTICLE_METHODS for m in methods):
        return None
    kind, why = filter_choice(config)
    if config.filter.kind != "auto":
        return f'filter: {kind} (kind "{kind}")'
    return f'filter: {kind} (kind "auto": {why})'
