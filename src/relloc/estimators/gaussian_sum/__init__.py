"""The self-calibrating Gaussian sum (``kind = "gaussian_sum"``): relative headings, odometry
scales and pair biases as states.

:mod:`.filter` is the Gaussian-sum filter, :mod:`.localizer` starts it from the particle
filter's annealed start and runs its cycle. ``auto`` picks it where headings or odometry
scales are estimated: the only kind that estimates them.
"""

from __future__ import annotations

from relloc.config import TeamConfig
from relloc.estimators.registry import Capabilities, Kind, register


def _suits(config: TeamConfig) -> str | None:
    sc = config.filter.self_calibration
    if sc.heading_mode == "estimate":
        return "headings estimated"
    if sc.odom_scale_mode == "online":
        return "odometry scales estimated"
    return None


KIND = register(
    Kind(
        "gaussian_sum",
        "relloc.estimators.gaussian_sum.localizer:SelfCalibratingLocalizer",
        Capabilities(headings=True, scales=True, online_biases=True),
        "the self-calibrating Gaussian sum: relative headings, odometry scales and pair biases "
        "as states",
        priority=10,
        suits=_suits,
    )
)
