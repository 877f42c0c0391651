"""What every estimator kind starts from and publishes at least: the prior of the online pair
biases (one belief per UWB node pair, :func:`bias_layout`), the covariance a published estimate
keeps per axis (:func:`covariance_floor`) and about the formation's rotation
(``ROTATION_FLOOR``). Shared by the kinds of :mod:`relloc.estimators`, so that one kind never
imports another's localizer for them.
"""

from __future__ import annotations

from relloc.config import TeamConfig
from relloc.events import pair_key
from relloc.filter.state import StateLayout

BIAS_PRIOR_SIGMA = 0.05
"""Online biases: prior standard deviation (m) of a calibrated pair's bias about its
calibration (the spread of the pair biases between sessions)."""
BIAS_PRIOR_SIGMA_UNCALIBRATED = 0.25
"""Online biases in the Gaussian-sum filter (headings or scales estimated as well): prior
standard deviation (m) of an uncalibrated pair's bias. The sampled filter uses
``uwb.default_bias_sigma`` instead, the width its default mode assumes for the same pair: a
wider prior let the bias run, on a new session, along what one range cannot tell apart (a
longer bias, a nearer robot) (docs/explanation/self-calibration.md, "Online bias on a new session")."""


def bias_layout(
    config: TeamConfig, *, uncalibrated_sigma: float | None = None
) -> tuple[StateLayout, list[float]]:
    """The sampled state's layout and the prior of its non-position columns: with online
    biases a (mean, variance) belief per UWB node pair of the team, none otherwise. An
    uncalibrated pair's prior is ``uwb.default_bias`` +- ``uncalibrated_sigma`` (default:
    ``BIAS_PRIOR_SIGMA_UNCALIBRATED``), a calibrated pair's its bias +- ``BIAS_PRIOR_SIGMA``."""
    fc = config.filter
    names = config.robot_names
    if fc.self_calibration.bias_mode != "online":
        return StateLayout(names, config.reference), []
    node_pairs = sorted(
        {_node_pair(config, a, b) for i, a in enumerate(names) for b in names[i + 1 :]}
    )
    prior: list[float] = []
    for pair in node_pairs:
        cal = config.uwb.pairs.get(pair)
        if cal is not None:
            prior += [cal.bias, BIAS_PRIOR_SIGMA**2]
        else:
            sigma = (
                BIAS_PRIOR_SIGMA_UNCALIBRATED if uncalibrated_sigma is None else uncalibrated_sigma
            )
            prior += [config.uwb.default_bias, sigma**2]
    return StateLayout(names, config.reference, tuple(node_pairs)), prior


def _node_pair(config: TeamConfig, robot_a: str, robot_b: str) -> str:
    """Key of the UWB transceiver pair between two robots (robot names if no node ids)."""
    a = config.robot(robot_a).uwb_node or robot_a
    b = config.robot(robot_b).uwb_node or robot_b
    return pair_key(a, b)


ROTATION_FLOOR = 0.05
"""Std (rad) of the formation's rotation that the published covariance keeps once the
orientation is resolved: a range error that follows the robots' headings (an antenna pattern)
turns the apparent motion of every robot alike, about its amplitude over the robots' turning
radius (docs/explanation/scaling.md: 2.5-3 degrees on the grid), which no fusion of ranges and odometry
can tell from a turn of the formation."""


def covariance_floor(config: TeamConfig, range_model: str) -> float:
    """Variance (m^2) per axis the filter adds to what it publishes: one range's noise under
    the localizer's range model (``[uwb] los_sigma``, or ``sigma`` for the symmetric model).
    Range errors are correlated in time, so fusing many cannot average them below that
    (:mod:`relloc.filter.summary`)."""
    sigma = config.uwb.los_sigma if range_model == "nlos" else config.uwb.sigma
    return float(sigma) ** 2
