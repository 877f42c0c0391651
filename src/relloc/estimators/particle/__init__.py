"""The sampled particle filter (``kind = "particle"``): the paper's filter.

:mod:`.filter` holds the particles and their update, :mod:`.localizer` starts it (annealed,
from the uniform prior) and runs its cycle. ``auto`` picks it for a team with odometry that
no other kind suits.
"""

from __future__ import annotations

from relloc.config import TeamConfig
from relloc.estimators.registry import Capabilities, Kind, register


def _suits(config: TeamConfig) -> str:
    return f"{len(config.robots)} robots with odometry"


KIND = register(
    Kind(
        "particle",
        "relloc.estimators.particle.localizer:ParticleFilterLocalizer",
        Capabilities(online_biases=True),
        "the sampled particle filter over the stacked relative positions (annealed start from "
        "the uniform prior, NLOS range mixture, online pair biases as particle states)",
        priority=100,
        suits=_suits,
    )
)
