"""Figures written into a Markdown page by the script that measured them, never by hand.

A page holds ``<!-- NAME figures: begin -->`` and ``<!-- NAME figures: end -->``; a script's
``--readme FILE`` replaces what lies between them with its run's table.
"""

from __future__ import annotations

from pathlib import Path


def markers(name: str) -> tuple[str, str]:
    """The begin and end markers of the section ``name``."""
    return f"<!-- {name} figures: begin -->", f"<!-- {name} figures: end -->"


def missing_section(path: Path, *names: str) -> str | None:
    """Why ``path`` cannot take the sections ``names`` (``None``: it can): checked before a
    benchmark measures for minutes, not after."""
    text = path.read_text() if path.is_file() else ""
    for name in names:
        if (problem := _problem(path, text, name)) is not None:
            return problem
    return None


def write_between(path: Path, name: str, body: str) -> None:
    """Replace the text between the markers of section ``name`` in ``path`` with ``body``; a
    page without them is an error (the figures would land nowhere a reader looks)."""
    text = path.read_text() if path.is_file() else ""
    problem = _problem(path, text, name)
    if problem is not None:
        raise SystemExit(problem)
    begin, end = markers(name)
    i, j = text.find(begin), text.find(end)
    path.write_text(text[: i + len(begin)] + "\n" + body + "\n" + text[j:])


def _problem(path: Path, text: str, name: str) -> str | None:
    begin, end = markers(name)
    i, j = text.find(begin), text.find(end)
    return f"{path} has no {begin} ... {end} section" if i < 0 or j < i else None
