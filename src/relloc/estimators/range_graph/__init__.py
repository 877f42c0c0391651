"""The range graph's Gaussian sum (``kind = "range_graph"``), for large teams with odometry.

:mod:`.filter` is the sparse information-form Gaussian sum, :mod:`.localizer` starts it from
the range graph's shape (:mod:`relloc.filter.range_shape`). ``auto`` never picks it (the
smoother is more accurate on large teams); it runs when named.
"""

from __future__ import annotations

from relloc.estimators.registry import Capabilities, Kind, register

KIND = register(
    Kind(
        "range_graph",
        "relloc.estimators.range_graph.localizer:RangeGraphLocalizer",
        Capabilities(),
        "a Gaussian sum started from the range graph (MDS, 72 orientation hypotheses), sparse "
        "information-form updates",
        priority=50,
    )
)
