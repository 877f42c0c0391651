"""What would make a run useless, checked before it starts: :class:`RunError` says which.

A run of minutes must not fail on its outputs at the end, nor score nothing because its
warm-up covers the whole source; both are errors before the first event.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

__all__ = ["RunError", "check_warmup", "check_writable"]


class RunError(Exception):
    """A problem with a run's input or options (the ``relloc`` command prints it as one line)."""


def check_writable(folder: Path, what: str = "--out") -> None:
    """Create ``folder`` and write a file in it, or raise :class:`RunError` now: a run must not
    fail on its outputs after minutes of work."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".relloc-write-check-"):
            pass
    except OSError as exc:
        raise RunError(f"cannot write to {what} {folder}: {exc.strerror or exc}") from None


def check_warmup(warmup: float, duration: float, name: str) -> None:
    """A warm-up at least as long as the run leaves nothing to score: an error before the run."""
    if warmup >= duration:
        raise RunError(
            f"--warmup {warmup:g} s is not shorter than {name} ({duration:.1f} s): every estimate "
            "would fall in the warm-up and no APE would be scored"
        )
