"""``relloc.malloc.tune_malloc``: freed NumPy temporaries stay mapped (no page faults on reuse)."""

from __future__ import annotations

import resource
import sys

import numpy as np
import pytest

from relloc.malloc import tune_malloc


def _faults_of_temporaries(n: int) -> int:
    """Minor page faults while allocating, touching and freeing ``n`` rounds of 1-2 MB arrays
    (a filter step's temporaries at 50 000 particles)."""
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        a = np.ones(150_000)  # 1.2 MB
        b = a * 2.0 + 1.0
        del a, b
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt")
def test_tuned_malloc_reuses_freed_temporaries_without_page_faults() -> None:
    assert tune_malloc() is True
    assert tune_malloc() is True  # idempotent
    _faults_of_temporaries(5)  # the heap grows once
    # Untuned, every round maps fresh pages: about 2 x 290 faults of 4 kB per round.
    assert _faults_of_temporaries(50) < 50
