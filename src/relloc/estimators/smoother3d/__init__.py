"""The 3D smoother (``kind = "smoother3d"``, GTSAM): flying teams' level poses.

:mod:`.graph` is the iSAM2 window of ``Pose3`` keys and its factors, :mod:`.start` the level
start from ranges and heights, :mod:`.localizer` the cycle and the estimate. ``auto`` picks it
for a team whose config says ``dimension = 3``; the 2D kinds refuse such a team.
"""

from __future__ import annotations

from relloc.config import TeamConfig
from relloc.estimators.registry import Capabilities, Kind, register


def _suits(config: TeamConfig) -> str | None:
    return "a flying team (dimension = 3)" if config.dimension == 3 else None


KIND = register(
    Kind(
        "smoother3d",
        "relloc.estimators.smoother3d.localizer:PoseSmootherLocalizer",
        Capabilities(
            headings=True,
            online_biases=True,
            sightings=False,
            detections=False,
            smoothed=True,
            dimensions=(3,),
        ),
        "a fixed-lag smoother of level poses (x, y, z, yaw) in 3D (GTSAM Pose3): body-frame "
        "odometry, heights, ranges between tags with lever arms, online pair biases",
        priority=10,
        suits=_suits,
    )
)
