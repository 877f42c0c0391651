"""A progress bar over a source's time, shared by ``relloc demo`` and ``relloc run``."""

from __future__ import annotations

from collections.abc import Iterable

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from relloc.engine import Engine
from relloc.events import Event


def run_with_progress(
    engine: Engine,
    events: Iterable[Event],
    *,
    label: str,
    duration: float,
    console: Console,
    enabled: bool = True,
    start: float | None = None,
) -> Engine:
    """``engine.run(events)`` with a bar of the source time covered out of ``duration`` seconds
    (``start``: the source's first time; default, the first event's)."""
    with Progress(
        TextColumn(f"[bold]{label}[/]"),
        BarColumn(),
        TextColumn("{task.completed:.1f}/{task.total:.1f} s"),
        TimeRemainingColumn(),
        console=console,
        disable=not enabled,
        transient=True,
    ) as bar:
        task = bar.add_task(label, total=max(duration, 1e-3))
        origin: list[float] = [] if start is None else [start]

        def progress(t: float) -> None:
            if not origin:
                origin.append(t)
            bar.update(task, completed=min(t - origin[0], duration))

        return engine.run(events, progress)
