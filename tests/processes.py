"""Starting relloc commands as separate processes, for the live tests."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def relloc(*args: str, log: Path) -> subprocess.Popen[bytes]:
    """Start ``relloc ARGS`` (this interpreter, from the repository root) with its output in
    ``log``."""
    with log.open("wb") as fh:
        return subprocess.Popen(
            [sys.executable, "-m", "relloc.cli", *args],
            stdout=fh,
            stderr=subprocess.STDOUT,
            cwd=REPO,
        )
