"""How a metric plugs into the report: the run it scores, what its result shows, the registry.

A metric is a class with a ``name`` and ``compute(run) -> MetricResult``. ``run`` is a
:class:`MethodRun`: one method's estimates, the ground truth, the robots, the warm-up and the
alignment the method is scored with. The result says where it shows itself, each part
optional (the defaults of :class:`MetricResult` show nothing):

* :meth:`MetricResult.robot_json` and :meth:`MetricResult.method_json`: fields of the method's
  JSON, per robot and for the method;
* :meth:`MetricResult.cells`: the text of its :attr:`Metric.columns` in the APE table, per robot
  (a column is placed by its ``rank``; one marked ``per_method`` is printed on the method's
  first row only);
* :meth:`MetricResult.tables`: tables of its own, printed after the APE table by
  :attr:`Metric.table_group` (all methods' tables of one group, then the next group);
* :attr:`Metric.caption`: a line explaining its columns, printed with the APE table.

:func:`register_metric` adds a class to :data:`METRICS`, which
:func:`relloc.evaluation.report.evaluate` computes for every method, in order: a new metric is
one registered class (:mod:`relloc.evaluation.scores` holds the shipped ones).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, ClassVar, TypeVar

from rich.table import Table

from relloc.estimate import Estimate
from relloc.evaluation.metrics import GroundTruth, Paired, after, associate

__all__ = ["METRICS", "Column", "MethodRun", "Metric", "MetricResult", "num", "register_metric"]


@dataclass(frozen=True)
class MethodRun:
    """One method's run, as every metric sees it.

    ``paired`` is the association of the estimates with the ground truth over the whole run,
    already aligned as the method is scored (``alignment``: ``"none"`` for the filters,
    ``"run"`` or ``"step"`` for multilateration and its oracle); metrics that judge the
    published uncertainty or shape score unaligned methods only (:attr:`aligned`).
    """

    method: str
    estimates: Sequence[Estimate]
    truth: GroundTruth
    robots: list[str]
    t0: float
    """Time of the run's first event."""
    warmup: float
    paired: dict[str, Paired]
    alignment: str = "none"
    reference: str = ""
    rotation: float = 0.0
    """The estimates' frame is the world turned by this angle (heading-estimate mode, rad)."""
    frame_rotation_deg: float | None = None
    """That rotation in degrees where the heading-estimate evaluation found it, else ``None``."""
    odometry_yaws: Mapping[str, Sequence[tuple[float, float]]] = field(default_factory=dict)
    """Per robot, ``(t, yaw)`` of its odometry at each estimate time (where the localizer keeps it)."""
    bias_truth: Mapping[str, float] = field(default_factory=dict)
    """Per node pair, the true range bias (where known) to score online bias estimates."""

    @property
    def start(self) -> float:
        """End of the warm-up: the figures count from here."""
        return self.t0 + self.warmup

    @property
    def aligned(self) -> bool:
        return self.alignment != "none"

    @cached_property
    def late(self) -> dict[str, Paired]:
        """``paired`` after the warm-up."""
        return {r: after(q, self.start) for r, q in self.paired.items()}

    @cached_property
    def shown(self) -> Sequence[Estimate]:
        """What the method published of each estimate (:meth:`Estimate.published`: the
        formation in its gauge where the orientation is not observable); an aligned method's
        estimates as they are."""
        return list(self.estimates) if self.aligned else [e.published() for e in self.estimates]

    @cached_property
    def published(self) -> dict[str, Paired]:
        """``shown`` associated with the ground truth over the whole run (an aligned method's:
        ``paired``, aligned as scored)."""
        if self.aligned:
            return self.paired
        return associate(self.shown, self.truth, self.robots, self.rotation)


@dataclass(frozen=True)
class Column:
    """A column of the APE table."""

    header: str
    rank: float = 100.0
    """Position among the table's columns, lowest first (the shipped ones use 10-61)."""
    per_method: bool = False
    """Printed on the method's first row only (a figure of the method, not of a robot)."""
    optional: bool = False
    """Left out of a table in which no row has it (a figure few runs have)."""


class MetricResult:
    """What a metric found for one method; each view defaults to showing nothing."""

    def robot_json(self) -> dict[str, dict[str, Any]]:
        """Per robot, fields of its JSON entry."""
        return {}

    def method_json(self) -> dict[str, Any]:
        """Fields of the method's JSON."""
        return {}

    def cells(self, robot: str) -> dict[str, str]:
        """The text of the metric's columns (by header) in ``robot``'s row."""
        return {}

    def tables(self, scenario: str, method: str) -> list[Table]:
        """Tables of its own for the method."""
        return []


class Metric(ABC):
    """A figure of a run: :func:`register_metric` makes the report compute it."""

    name: ClassVar[str]
    """Its key in :attr:`relloc.evaluation.report.MethodReport.results`."""
    columns: ClassVar[tuple[Column, ...]] = ()
    caption: ClassVar[str | None] = None
    table_group: ClassVar[int] = 0

    @abstractmethod
    def compute(self, run: MethodRun) -> MetricResult:
        """The metric's result for one method's run."""


M = TypeVar("M", bound=type[Metric])

METRICS: list[type[Metric]] = []
"""The registered metrics, in the order their fields and tables appear."""


def register_metric(cls: M) -> M:
    """Class decorator: compute ``cls`` for every method of every report from now on."""
    METRICS.append(cls)
    return cls


def num(x: float | None) -> float | None:
    """A figure for JSON: rounded to 5 decimals, ``None`` where not finite."""
    return None if x is None or not math.isfinite(x) else round(float(x), 5)
