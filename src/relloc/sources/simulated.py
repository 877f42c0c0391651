"""A simulated team (:mod:`relloc.simulator`) as a :class:`~relloc.sources.protocol.Source`.

The open-loop run of a :class:`~relloc.simulator.Simulation` from its start, with the
simulation's truthful team config; the counters are those of the recorded sources
(:class:`~relloc.sources.ingest.IngestStats`: events per kind, nothing rejected).
"""

from __future__ import annotations

from collections.abc import Iterator

from relloc.config import TeamConfig
from relloc.events import Event
from relloc.simulator import Simulation
from relloc.sources.ingest import IngestStats
from relloc.sources.protocol import Pose


class SimulationSource:
    """The events of ``simulation``'s open-loop run, named ``name`` (default: its config's)."""

    def __init__(self, simulation: Simulation, name: str | None = None) -> None:
        self.simulation = simulation
        self.name = name or simulation.config.name
        self.config: TeamConfig = simulation.config
        self.warnings: list[str] = []
        self.stats = IngestStats()
        self.start_time = 0.0

    @property
    def duration(self) -> float:
        return self.simulation.duration

    def __iter__(self) -> Iterator[Event]:
        self.stats = stats = IngestStats()
        for event in self.simulation.events():
            stats.emitted(event)
            yield event

    def initial_poses(self) -> dict[str, Pose]:
        """Every robot's true pose at ``t = 0``."""
        return {robot: self.simulation.true_pose(robot, 0.0) for robot in self.simulation.robots}
