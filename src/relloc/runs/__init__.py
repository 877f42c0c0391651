"""Runs and sweeps as a library: what ``relloc run`` and ``relloc demo`` do, without the command line.

* :func:`run_recording` (:mod:`.recording`): a source (a rosbag2 recording, an MRCLAM data set, a
  simulated scenario's name) through every method of :class:`RunOptions`, evaluated against its
  ground truth; plots, TUM trajectories, MCAP and JSON written where the options say.
* :func:`run_demo` (:mod:`.demo`): the simulated scenarios of :class:`DemoOptions`, the same way.
* :func:`sweep` (:mod:`.sweep`): many ``relloc`` runs, each in its own process, their JSON
  figures collected (seeds, references, filter kinds of a results page).

Each prints its tables to a :class:`rich.console.Console` (an optional argument: the standard
output's by default) and raises :class:`RunError` before it starts when it could score nothing
or write nowhere. The ``relloc`` command parses its arguments into these options and calls them.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# light (the standard library only), and imported now: the function ``sweep`` must shadow the
# module of its name on this package
from relloc.runs.checks import RunError
from relloc.runs.sweep import SweepError, SweepJob, SweepResult, run_jobs, sweep

if TYPE_CHECKING:
    from relloc.runs.demo import DemoOptions, run_demo
    from relloc.runs.recording import RunOptions, run_recording

_HOME = {
    "DemoOptions": "demo",
    "run_demo": "demo",
    "RunOptions": "recording",
    "run_recording": "recording",
}
"""The heavy names' modules, imported on first use: a sweep or the command's start needs no
engine."""

__all__ = [
    "DemoOptions",
    "RunError",
    "RunOptions",
    "SweepError",
    "SweepJob",
    "SweepResult",
    "run_demo",
    "run_jobs",
    "run_recording",
    "sweep",
]


def __getattr__(name: str) -> Any:
    if name not in _HOME:
        raise AttributeError(f"module 'relloc.runs' has no attribute {name!r}")
    return getattr(importlib.import_module(f"relloc.runs.{_HOME[name]}"), name)
