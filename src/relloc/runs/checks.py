"""What would make a run useless, checked before it starts: :class:`RunError` says which.

:func:`runnable` keeps the methods a team can run (a flying team runs no planar method) and
says which it skips.

A run of minutes must not fail on its outputs at the end, nor score nothing because its
warm-up covers the whole source; both are errors before the first event.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from relloc.config import TeamConfig
from relloc.methods import cannot_run

__all__ = ["RunError", "check_warmup", "check_writable", "runnable"]


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


def runnable(methods: Sequence[str], config: TeamConfig, console: Console, name: str) -> list[str]:
    """The ``methods`` the team can run (:func:`relloc.methods.cannot_run`: a planar method
    for a flying team), each other one said on ``console`` and skipped; a :class:`RunError`
    where none is left."""
    out = []
    for method in methods:
        why = cannot_run(method, config)
        if why is None:
            out.append(method)
        else:
            console.print(f"{name}: {why}: not run", soft_wrap=True, highlight=False, markup=False)
    if not out:
        raise RunError(f"{name}: none of the methods {', '.join(methods)} can run for this team")
    return out
