"""Many ``relloc`` runs, each in its own process, their JSON figures collected.

A results page is a sweep: seeds, references, filter kinds, each one ``relloc run ... --json F``.
Each run is a subprocess (``sys.executable -m relloc.cli``), so a crash or a leak of one run
stays its own and the figures are exactly those the command writes; a thread pool keeps
``workers`` of them going at once.

    jobs = [SweepJob(("run", "single", "--seed", str(s), "--no-progress"), out / f"s{s}.json")
            for s in range(5)]
    payloads = sweep(jobs, workers=2)  # each run's JSON, in the order of jobs

:func:`sweep` raises :class:`SweepError` naming the first failed job with the tail of its
standard error; :func:`run_jobs` returns every :class:`SweepResult` (the run's output, exit
status and wall time) and leaves failures to the caller.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["SweepError", "SweepJob", "SweepResult", "run_job", "run_jobs", "sweep"]

TAIL_CHARS = 2000
"""How much of a failed run's standard error its error message quotes."""


@dataclass(frozen=True)
class SweepJob:
    """One ``relloc`` run: its arguments (without ``--json``) and where its JSON goes."""

    argv: Sequence[str]
    """The ``relloc`` arguments, e.g. ``("run", "single", "--seed", "1", "--no-progress")``."""
    json_path: Path
    """The run's ``--json`` file (removed before the run: no stale figures)."""
    name: str | None = None
    """What errors call the job (default: the JSON file's stem)."""
    env: Mapping[str, str] = field(default_factory=dict)
    """Variables added to the environment (e.g. ``OMP_NUM_THREADS``)."""
    cwd: Path | None = None
    """The run's working directory (default: this process's)."""
    timeout: float | None = None
    """Seconds before the run is stopped and counted as failed."""

    @property
    def label(self) -> str:
        return self.name or self.json_path.stem

    def command(self) -> list[str]:
        """The whole command line of the run."""
        return [sys.executable, "-m", "relloc.cli", *self.argv, "--json", str(self.json_path)]


@dataclass(frozen=True)
class SweepResult:
    """What one job gave: its JSON (``None`` when it failed), its output and its wall time."""

    job: SweepJob
    payload: dict[str, Any] | None
    returncode: int | None
    """The exit status; ``None`` when the run went over the job's timeout."""
    stdout: str
    stderr: str
    wall_s: float

    @property
    def ok(self) -> bool:
        return self.payload is not None

    @property
    def error(self) -> str | None:
        """Why the job failed in a few words (``None`` when it did not)."""
        if self.returncode is None:
            return f"over {self.job.timeout:.0f} s"
        if self.returncode != 0:
            return f"exit {self.returncode}"
        if self.payload is None:
            return f"no JSON written to {self.job.json_path}"
        return None

    def last_line(self) -> str:
        """The last line the run printed (standard error first), else :attr:`error`."""
        lines = (self.stderr or self.stdout).strip().splitlines()
        return lines[-1] if lines else (self.error or "")

    def message(self) -> str:
        """The job, why it failed and the tail of its standard error."""
        tail = self.stderr[-TAIL_CHARS:].rstrip()
        return f"{self.job.label} failed ({self.error}): {' '.join(self.job.command())}" + (
            f"\n{tail}" if tail else ""
        )


class SweepError(RuntimeError):
    """A job of :func:`sweep` failed; :attr:`result` holds its output."""

    def __init__(self, result: SweepResult) -> None:
        super().__init__(result.message())
        self.result = result


def run_job(job: SweepJob) -> SweepResult:
    """Run ``job`` in a subprocess and read its JSON."""
    job.json_path.unlink(missing_ok=True)
    job.json_path.parent.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, **job.env} if job.env else None
    start = time.perf_counter()
    try:
        done = subprocess.run(
            job.command(), capture_output=True, text=True, env=env, cwd=job.cwd, timeout=job.timeout
        )
    except subprocess.TimeoutExpired as exc:
        return SweepResult(
            job, None, None, _text(exc.stdout), _text(exc.stderr), job.timeout or 0.0
        )
    wall = time.perf_counter() - start
    payload = None
    if done.returncode == 0 and job.json_path.is_file():
        payload = json.loads(job.json_path.read_text())
    return SweepResult(job, payload, done.returncode, done.stdout, done.stderr, wall)


def run_jobs(
    jobs: Sequence[SweepJob],
    workers: int = 1,
    on_done: Callable[[SweepResult], None] | None = None,
) -> list[SweepResult]:
    """Every job's :class:`SweepResult`, in the order of ``jobs``, ``workers`` at a time;
    ``on_done`` is called with each as it finishes (in a worker thread)."""

    def one(job: SweepJob) -> SweepResult:
        result = run_job(job)
        if on_done is not None:
            on_done(result)
        return result

    if workers <= 1 or len(jobs) <= 1:
        return [one(job) for job in jobs]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(one, jobs))


def sweep(jobs: Sequence[SweepJob], workers: int = 1) -> list[dict[str, Any]]:
    """Each job's JSON, in the order of ``jobs``; :class:`SweepError` for the first that failed
    (every job has run by then)."""
    results = run_jobs(jobs, workers)
    for result in results:
        if result.payload is None:
            raise SweepError(result)
    return [r.payload for r in results if r.payload is not None]


def _text(out: str | bytes | None) -> str:
    if isinstance(out, bytes):
        return out.decode(errors="replace")
    return out or ""
