"""Whether the particle filter's step runs as compiled passes (numba) or as NumPy calls.

Both paths compute the same step; the compiled one draws its motion noise from its own stream
(:mod:`relloc.filter.motion`), so a seeded run gives other numbers than the NumPy path. The
compiled passes run when numba imports and ``RELLOC_COMPILED`` is not ``0``; tests and scripts
may set :data:`ENABLED` (read on every step) to compare the paths seed by seed.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

numba: Any
try:
    import numba
except ImportError:  # pragma: no cover - numba is a core dependency; this keeps NumPy usable
    numba = None

AVAILABLE = numba is not None
"""Whether numba imports."""
ENABLED = AVAILABLE and os.environ.get("RELLOC_COMPILED", "1") != "0"
"""Whether the particle filter's step takes its compiled passes (read on every step)."""


def njit(*args: Any, **kwargs: Any) -> Callable[..., Any]:
    """``numba.njit`` where numba imports; otherwise the function as written (the NumPy path
    never calls it then)."""
    if numba is not None:
        return numba.njit(*args, **kwargs)  # type: ignore[no-any-return,unused-ignore]

    def plain(function: Callable[..., Any]) -> Callable[..., Any]:
        return function

    return plain


def enabled() -> bool:
    """:data:`ENABLED`, as it is now."""
    return ENABLED
