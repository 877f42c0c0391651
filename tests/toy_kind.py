"""An estimator kind relloc has never heard of, in this one module: the plug-in of
``tests/test_estimator_kinds.py``.

The *last range* kind places each robot on the reference's x axis at its last range to the
reference (a sensible guess only for a team in a line; its covariance says how little it
knows). It registers itself on import, as a package of :mod:`relloc.estimators` does, and
``auto`` picks it for a team named ``line``.
"""

from __future__ import annotations

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.estimators import Capabilities, Kind, register
from relloc.events import RangeEvent
from relloc.localizers.base import Localizer, Measurement

SPREAD = 2.0
"""Std (m) of the published position along y: a range says nothing about the direction."""


class LastRangeLocalizer(Localizer):
    """Each robot at its last range to the reference, on the x axis (module docstring)."""

    def __init__(self, config: TeamConfig, *, seed: int = 0, method: str = "pf") -> None:
        super().__init__(config)
        self.method = method
        self.last: dict[str, float] = {}

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        ref = self.layout.reference
        for m in batch:
            if isinstance(m, RangeEvent) and ref in (m.robot_a, m.robot_b):
                other = m.robot_b if m.robot_a == ref else m.robot_a
                self.last[other] = m.distance
        if not self.last:
            return None
        positions = {r: (d, 0.0) for r, d in self.last.items()}
        covariances = {r: ((0.1, 0.0), (0.0, SPREAD**2)) for r in self.last}
        return Estimate(t, self.method, ref, positions, covariances)


def _suits(config: TeamConfig) -> str | None:
    return "a team in a line" if config.name == "line" else None


KIND = register(
    Kind(
        "last_range",
        f"{__name__}:LastRangeLocalizer",
        Capabilities(sightings=False, detections=False),
        "each robot at its last range to the reference, on the x axis",
        priority=0,
        suits=_suits,
    )
)
