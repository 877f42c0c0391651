"""Whether the particle filter's step runs as compiled passes (numba) or as NumPy calls.

Both paths compute the same step; the compiled one draws its motion noise from its own stream
(:mod:`relloc.filter.motion`), so a seeded run gives other numbers than the NumPy path. The
compiled passes run when numba is installed and ``RELLOC_COMPILED`` is not ``0``; tests and
scripts may set :data:`ENABLED` (read on every step) to compare the paths seed by seed. ``relloc
serve`` takes the NumPy step unless told otherwise (:func:`serve_default`, :func:`chosen`).

numba is imported lazily: :func:`njit` wraps each kernel in a :class:`LazyKernel`, and only the
first call of one while :data:`ENABLED` holds imports numba (about 130 MB of resident memory,
libllvmlite and scipy among it) and compiles. A process on the NumPy path (``relloc serve`` by
default) never imports it.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

AVAILABLE = importlib.util.find_spec("numba") is not None
"""Whether numba is installed (looked up without importing it)."""
ENABLED = AVAILABLE and os.environ.get("RELLOC_COMPILED", "1") != "0"
"""Whether the particle filter's step takes its compiled passes (read on every step)."""

_KERNELS: list[LazyKernel] = []
_LOCK = threading.Lock()
_compiled = False


class LazyKernel:
    """A kernel written for ``numba.njit``, not yet compiled.

    Called while :data:`ENABLED` holds, it compiles every registered kernel (:func:`compile_all`)
    and calls its dispatcher; otherwise it runs the function as written (same results, Python
    speed: the NumPy path is not meant to call kernels)."""

    def __init__(self, function: Callable[..., Any], options: dict[str, Any]) -> None:
        self.py_func = function
        self.options = options
        self.dispatcher: Any = None
        self.__name__ = function.__name__
        self.__qualname__ = function.__qualname__
        self.__module__ = function.__module__
        self.__doc__ = function.__doc__
        self.__wrapped__ = function

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if self.dispatcher is None:
            if not enabled():
                return self.py_func(*args, **kwargs)
            compile_all()
        return self.dispatcher(*args, **kwargs)


def compile_all() -> None:
    """Import numba and turn every :class:`LazyKernel` into its ``numba.njit`` dispatcher, also
    in the namespaces of the loaded ``relloc`` modules (numba resolves a kernel's callees by
    their globals when it compiles, so they must be dispatchers by then)."""
    global _compiled
    with _LOCK:
        if _compiled:
            return
        import numba

        swap: dict[int, Any] = {}
        for kernel in _KERNELS:
            kernel.dispatcher = numba.njit(**kernel.options)(kernel.py_func)
            swap[id(kernel)] = kernel.dispatcher
        for name, module in list(sys.modules.items()):
            if name.split(".", 1)[0] != "relloc" or module is None:
                continue
            namespace = vars(module)
            for key, value in list(namespace.items()):
                if isinstance(value, LazyKernel) and id(value) in swap:
                    namespace[key] = swap[id(value)]
        _compiled = True


def njit(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    """``numba.njit(**options)``, deferred: the function wrapped in a :class:`LazyKernel`."""

    def wrap(function: Callable[..., Any]) -> LazyKernel:
        kernel = LazyKernel(function, options)
        with _LOCK:
            _KERNELS.append(kernel)
            done = _compiled
        if done:  # a kernel module loaded after the others compiled
            import numba

            kernel.dispatcher = numba.njit(**options)(function)
            return kernel.dispatcher
        return kernel

    return wrap


def serve_default() -> bool:
    """Whether ``relloc serve`` takes the compiled step when its options do not say: only where
    ``RELLOC_COMPILED=1`` is set. numba's import alone holds about 130 MB resident, more than a
    serve's 100 MB budget; the NumPy step costs a serve more CPU instead (docs/howto/live-robots.md)."""
    return AVAILABLE and os.environ.get("RELLOC_COMPILED") == "1"


_CHOICE = threading.local()
"""This thread's choice while in :func:`chosen` (``value``), else none."""


@contextmanager
def chosen(compiled: bool) -> Iterator[None]:
    """The step set to ``compiled`` (never where numba is missing or ``RELLOC_COMPILED=0``) for
    the block, in this thread only, and restored after it: a serve's choice does not outlive its
    run, nor reaches another thread (servers of one process, an offline run beside them), and
    :data:`ENABLED` is left as it is."""
    previous = getattr(_CHOICE, "value", None)
    _CHOICE.value = compiled and AVAILABLE and os.environ.get("RELLOC_COMPILED", "1") != "0"
    try:
        yield
    finally:
        _CHOICE.value = previous


def enabled() -> bool:
    """Whether the step takes its compiled passes in this thread: its :func:`chosen` block's
    choice, else :data:`ENABLED` as it is now (read on every step)."""
    value = getattr(_CHOICE, "value", None)
    return ENABLED if value is None else bool(value)
