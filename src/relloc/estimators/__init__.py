"""Estimator kinds (``[filter] kind``), one package each, and their registry.

Each kind registers itself (:mod:`.registry`) with what it can do; importing this package
registers the built-in ones: :mod:`.particle`, :mod:`.gaussian_sum`, :mod:`.range_graph`,
:mod:`.smoother`, :mod:`.smoother3d`. A kind of one's own is one module that calls :func:`register` with a
:class:`Kind` (docs/howto/extending.md).
"""

from __future__ import annotations

from relloc.estimators import gaussian_sum, particle, range_graph, smoother, smoother3d
from relloc.estimators.registry import (
    KINDS,
    Capabilities,
    Estimator,
    Kind,
    check,
    choose,
    get,
    names,
    register,
    unregister,
)

__all__ = [
    "KINDS",
    "Capabilities",
    "Estimator",
    "Kind",
    "check",
    "choose",
    "gaussian_sum",
    "get",
    "names",
    "particle",
    "range_graph",
    "register",
    "smoother",
    "smoother3d",
    "unregister",
]
