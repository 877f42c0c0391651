"""What a process of the live engine costs, read from ``/proc`` (Linux): its CPU time, sampled on
a thread of its own so that any window of a run can be read afterwards, its peak and current
resident memory, the CPU time of each of its threads, and percentiles of measured latencies.

The measuring tools of ``benchmarks/serve_resources.py`` (``relloc serve`` as a subprocess) and
``benchmarks/serve_vs_subscriber.py``; nothing in the engine imports them.
"""

from __future__ import annotations

import math
import os
import statistics
import threading
import time
from pathlib import Path

__all__ = [
    "CpuSampler",
    "percentiles",
    "proc_cpu_seconds",
    "proc_memory_mb",
    "round_finite",
    "thread_cpu_seconds",
]


def proc_cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (s), from ``/proc/<pid>/stat``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def proc_memory_mb(pid: int) -> dict[str, float]:
    """``VmHWM`` (peak RSS), ``VmRSS`` and its parts ``RssAnon`` (the process's own memory) and
    ``RssFile`` (mapped files: mostly shared libraries, resident once for all processes that map
    them) of a process in MB, from ``/proc/<pid>/status``."""
    out: dict[str, float] = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in ("VmHWM", "VmRSS", "RssAnon", "RssFile"):
            out[name] = int(value.split()[0]) / 1024.0
    return out


def thread_cpu_seconds(pid: int) -> dict[str, float]:
    """CPU time (s) of each thread of a process, summed by thread name (``comm``), from
    ``/proc/<pid>/task/*/stat``: tells the engine thread from Zenoh's and any BLAS pool."""
    out: dict[str, float] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            text = (task / "stat").read_text()
        except OSError:
            continue  # the thread ended
        name = text[text.index("(") + 1 : text.rindex(")")]
        fields = text.rsplit(")", 1)[1].split()
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick
    return out


class CpuSampler:
    """Samples a process's CPU time every ``period`` seconds on a thread of its own, so that
    the CPU of any window of the run (after convergence) can be read afterwards."""

    def __init__(self, pid: int, period: float = 0.25) -> None:
        self.pid = pid
        self.period = period
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.samples.append((time.time(), proc_cpu_seconds(self.pid)))
            except OSError:
                return
            self._stop.wait(self.period)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def percent_between(self, t0: float, t1: float) -> float:
        """CPU % of one core between the samples nearest after ``t0`` and before ``t1``."""
        inside = [s for s in self.samples if t0 <= s[0] <= t1]
        if len(inside) < 2 or inside[-1][0] - inside[0][0] <= 0.0:
            return math.nan
        return 100.0 * (inside[-1][1] - inside[0][1]) / (inside[-1][0] - inside[0][0])


def percentiles(values: list[float]) -> dict[str, float | int | None]:
    """Median, 95th percentile and maximum of latencies given in seconds, in milliseconds, and
    their count (``None`` each when there are none)."""
    if not values:
        return {"p50_ms": None, "p95_ms": None, "max_ms": None, "n": 0}
    v = sorted(values)

    def q(f: float) -> float:
        return v[min(len(v) - 1, max(0, math.ceil(f * len(v)) - 1))]

    return {
        "p50_ms": round(1e3 * statistics.median(v), 3),
        "p95_ms": round(1e3 * q(0.95), 3),
        "max_ms": round(1e3 * v[-1], 3),
        "n": len(v),
    }


def round_finite(x: float, nd: int = 3) -> float | None:
    """``x`` rounded to ``nd`` decimals, ``None`` when it is not finite (JSON has no NaN)."""
    return None if x is None or not math.isfinite(x) else round(float(x), nd)
