"""The fixed-lag factor-graph smoother (``kind = "smoother"``, GTSAM), where ranges dominate.

:mod:`.graph` is the iSAM2 window and its factors, :mod:`.moments` the published moments,
:mod:`.localizer` the cycle, the start's hypotheses and the smoothed run. ``auto`` picks it for
a team with a robot without odometry, and for a large team in the shared heading frame
(``LARGE_TEAM_ROBOTS``, docs/explanation/scaling.md).
"""

from __future__ import annotations

from relloc.config import TeamConfig
from relloc.estimators.registry import Capabilities, Kind, register

LARGE_TEAM_ROBOTS = 12
"""Teams of at least this many robots are large to the automatic choice (docs/explanation/scaling.md)."""


def large_compass_team(config: TeamConfig) -> bool:
    """Whether ``config`` is a large team for the automatic choice: ``LARGE_TEAM_ROBOTS`` or
    more in the shared heading frame with fixed odometry scales and calibrated (not online)
    biases."""
    sc = config.filter.self_calibration
    return (
        len(config.robot_names) >= LARGE_TEAM_ROBOTS
        and sc.heading_mode != "estimate"
        and sc.odom_scale_mode != "online"
        and sc.bias_mode != "online"
    )


def _suits(config: TeamConfig) -> str | None:
    n = len(config.robots)
    without = [r.name for r in config.robots if not r.odom_topic]
    if without:
        who = f"{len(without)} of {n} robots without odometry"
        if config.filter.self_calibration.bias_mode == "online":
            return f"{who}, biases online"
        return who
    if large_compass_team(config):
        return f"{n} robots, a large team"
    return None


KIND = register(
    Kind(
        "smoother",
        "relloc.estimators.smoother.localizer:SmootherLocalizer",
        Capabilities(online_biases=True, smoothed=True),
        "a fixed-lag factor-graph smoother (GTSAM): robust range factors, odometry factors or a "
        "bounded-speed motion prior, sightings and detections as relative-position factors, "
        "online pair biases held constant",
        priority=20,
        suits=_suits,
    )
)
