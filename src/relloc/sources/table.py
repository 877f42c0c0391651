"""Which source a path names: one table for ``relloc run``, ``calibrate`` and ``replay``.

=============  ==============================================================  ========================
kind           what the path is                                                source
=============  ==============================================================  ========================
``rosbag2``    a folder with ``metadata.yaml``, or a ``.db3``/``.mcap`` file     :class:`RosbagSource`
``mrclam``     a folder with ``Barcodes.dat`` and ``Robot1_Odometry.dat``        :class:`MrclamSource`
``scenario``   a simulated scenario's name (not an existing path)              :class:`SimulationSource`
=============  ==============================================================  ========================

:func:`source_kind` looks a path up (the first row that matches, in this order: an existing path
is never taken for a scenario's name); anything else is a :class:`SourceError` that lists the
three. Each row says what the commands may do with it (:attr:`SourceKind.replayable`,
:attr:`SourceKind.calibrates`) and opens its source (:meth:`SourceKind.open`), so no caller
tests a source's class. A new source is one row.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from relloc.config import TeamConfig
from relloc.simulator.scenarios import SCENARIOS
from relloc.sources.mrclam import MrclamSource, is_mrclam
from relloc.sources.protocol import Source
from relloc.sources.rosbag import RosbagSource
from relloc.sources.simulated import SimulationSource

__all__ = ["KINDS", "SourceError", "SourceKind", "SourceOptions", "open_source", "source_kind"]


class SourceError(Exception):
    """The path is no known source, or not one the command can use (one line)."""


@dataclass(frozen=True)
class SourceOptions:
    """What a run asks of its source, whichever it is."""

    seed: int = 0
    """Seed of a simulated scenario."""
    sightings: str = "both"
    """What of each teammate sighting to pass on (MRCLAM): ``both``, ``range``, ``bearing``."""
    detections: bool = False
    """Whether a simulated scenario simulates the cameras' object detections."""


@dataclass(frozen=True)
class SourceKind:
    """One row of the table."""

    name: str
    what: str
    """What such a path is, as error messages say it."""
    matches: Callable[[Path], bool]
    opener: Callable[[Path, TeamConfig | None, SourceOptions], Source]
    truth_name: str
    """What the run scores the estimates against."""
    needs_config: bool = True
    """Whether the user gives the team config (a simulation brings its own)."""
    replayable: bool = False
    """Raw ROS 2 messages that ``relloc replay`` can publish."""
    calibrates: bool = False
    """UWB ranges with motion capture: ``relloc calibrate`` estimates the pair biases from
    it, and a run with online biases scores them against the same measurement."""

    def open(
        self, path: str | Path, config: TeamConfig | None, options: SourceOptions | None = None
    ) -> Source:
        """The source at ``path`` for ``config`` (``None`` where the kind brings its own)."""
        if config is None and self.needs_config:
            raise SourceError(f"{path} is {self.what}: it needs a team config (--config)")
        return self.opener(Path(path), config, options or SourceOptions())


def _is_bag(path: Path) -> bool:
    return (path.is_dir() and (path / "metadata.yaml").exists()) or (
        path.is_file() and path.suffix in (".db3", ".mcap")
    )


def _is_scenario(path: Path) -> bool:
    return not path.exists() and str(path) in SCENARIOS


def _open_bag(path: Path, config: TeamConfig | None, options: SourceOptions) -> Source:
    assert config is not None
    source = RosbagSource(path, config)
    source.check_ranges()
    return source


def _open_mrclam(path: Path, config: TeamConfig | None, options: SourceOptions) -> Source:
    assert config is not None
    return MrclamSource(path, config, sightings=options.sightings)


def _open_scenario(path: Path, config: TeamConfig | None, options: SourceOptions) -> Source:
    if config is not None:
        raise SourceError(
            f"the simulated scenario {path} brings its own team config: leave out --config"
        )
    name = str(path)
    return SimulationSource(SCENARIOS[name](options.seed, detections=options.detections), name)


KINDS: tuple[SourceKind, ...] = (
    SourceKind(
        "rosbag2",
        "a rosbag2 recording",
        _is_bag,
        _open_bag,
        "motion capture",
        replayable=True,
        calibrates=True,
    ),
    SourceKind("mrclam", "an MRCLAM data set", is_mrclam, _open_mrclam, "motion capture"),
    SourceKind(
        "scenario",
        "a simulated scenario",
        _is_scenario,
        _open_scenario,
        "ground truth",
        needs_config=False,
    ),
)
"""The table, in lookup order."""


def source_kind(path: str | Path) -> SourceKind:
    """The row of ``path``, or a :class:`SourceError` saying what a source path may be."""
    p = Path(path)
    for kind in KINDS:
        if kind.matches(p):
            return kind
    problem = "not found" if not p.exists() else "not a source"
    raise SourceError(
        f"{path}: {problem}; give a rosbag2 recording (a folder with metadata.yaml, or a .db3/.mcap "
        "file), an MRCLAM data set folder (Barcodes.dat, Robot1_Odometry.dat) or a simulated "
        f"scenario ({', '.join(SCENARIOS)})"
    )


def open_source(
    path: str | Path, config: TeamConfig | None, options: SourceOptions | None = None
) -> Source:
    """The source ``path`` names (:func:`source_kind`), opened for ``config``."""
    return source_kind(path).open(path, config, options)
