"""Keep the C allocator from handing freed memory back to the kernel between filter steps.

A filter step allocates and frees dozens of NumPy temporaries of ``M`` particles (tens of kB
to a few MB each). With glibc's default settings a freed block at the top of the heap beyond
``M_TRIM_THRESHOLD`` (128 kB, adapted upwards at run time) is returned to the kernel, and a
block above ``M_MMAP_THRESHOLD`` gets its own ``mmap``: the next step's temporaries then touch
fresh pages, and every 4 kB page costs a minor page fault (a few microseconds on a virtual
machine), which can be a large share of a small filter step's time. :func:`tune_malloc` keeps a pad of heap instead, so those pages stay mapped and are
reused; it changes no result, only where the memory comes from.

It is a process-wide setting, so the library never calls it on import: the ``relloc``
command does at start (every command, ``serve`` included), and so do the benchmarks. Other
programs that embed relloc may call it themselves. On a C library other than glibc it does
nothing.
"""

from __future__ import annotations

import ctypes
import sys

_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3

TOP_PAD = 64 << 20
"""Heap kept beyond what is in use when it grows or shrinks (bytes): only pages ever touched
are resident, so this costs no memory by itself."""
TRIM_THRESHOLD = 128 << 20
"""Free heap at the top (bytes) above which glibc returns memory to the kernel."""
MMAP_THRESHOLD = 32 << 20
"""Blocks at least this large (bytes) still get their own mapping (glibc's largest adaptive
value on 64-bit), so a huge temporary is returned to the kernel when freed."""

_done: bool | None = None


def tune_malloc() -> bool:
    """Set glibc's ``M_TOP_PAD``, ``M_TRIM_THRESHOLD`` and ``M_MMAP_THRESHOLD`` (module
    docstring); True if they are set (now or by an earlier call), False where there is no
    glibc ``mallopt``. Idempotent."""
    global _done
    if _done is not None:
        return _done
    _done = False
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library Python itself runs on (no search)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = all(
        mallopt(param, value) == 1
        for param, value in (
            (_M_TOP_PAD, TOP_PAD),
            (_M_TRIM_THRESHOLD, TRIM_THRESHOLD),
            (_M_MMAP_THRESHOLD, MMAP_THRESHOLD),
        )
    )
    _done = ok
    return ok
