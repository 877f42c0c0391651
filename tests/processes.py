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


def write_sim_team(path: Path, scenario: str = "multi", particles: int = 500) -> Path:
    """The simulated ``scenario``'s team config, written to ``path`` by ``relloc sim-robots
    --config-only`` (the config a live test then serves)."""
    made = subprocess.run(
        [sys.executable, "-m", "relloc.cli", "sim-robots", "--scenario", scenario,
         "--config-only", "--write-config", str(path), "--particles", str(particles)],
        capture_output=True, text=True, cwd=REPO, timeout=60,
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    return path
