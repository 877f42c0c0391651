"""Generated pages: figures written into a Markdown page by the script that measured them, never
by hand.

A page holds ``<!-- NAME figures: begin -->`` and ``<!-- NAME figures: end -->``; a benchmark's or
script's ``--readme FILE`` replaces what lies between them with its run's table
(:func:`write_between`), after checking before it measures that the page can take it
(:func:`missing_section`). :func:`figure_runs` is the table of evaluation runs whose figures a
refactor must leave unchanged (``scripts/figures_check.py``) and that the results page reruns
(``scripts/results_pages.py``).
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


def check_page_args(page: Path | None, section: str | None) -> None:
    """Exit before any work where a script's ``--page`` and ``--section`` cannot be written:
    one without the other, or a page without the section's markers."""
    if (page is None) != (section is None):
        raise SystemExit("--page and --section go together")
    problem = None if page is None or section is None else missing_section(page, section)
    if problem is not None:
        raise SystemExit(problem)


def print_table(lines: list[str], page: Path | None, section: str | None) -> None:
    """Print a table's ``lines``; with a ``page`` (:func:`check_page_args`), write them between
    the markers of its ``section`` too."""
    text = "\n".join(lines)
    print(text)
    if page is not None and section is not None:
        write_between(page, section, text)


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


def figure_runs(data: Path) -> dict[str, list[str]]:
    """The evaluation runs whose figures a refactor must leave unchanged: name to ``relloc``
    arguments, the recordings read under ``data`` (the shared data folder)."""
    tiers = data / "tiers"
    shortbag = [
        "run",
        str(tiers / "multi4_shortbag_20221011"),
        "--config",
        "configs/tiers/multi4_shortbag_20221011.toml",
        "--methods",
        "pf",
    ]
    pair = [
        "run",
        str(tiers / "pair_range_20220907_1725"),
        "--config",
        "configs/tiers/pair_range_20220907_1725.toml",
        "--warmup",
        "10",
    ]
    table = {
        "demo": ["demo", "--seed", "0"],
        "demo_selfcal": [
            "demo",
            "--seed",
            "0",
            "--heading",
            "estimate",
            "--bias",
            "online",
            "--warmup",
            "20",
            "--scenarios",
            "multi",
        ],
        "pair_range": pair,
        "pair_range_online": [*pair, "--bias", "online"],
        "case4_static": [
            "run",
            str(data / "tiers_uwb_rel" / "case4_test1_static"),
            "--config",
            "configs/tiers_uwb_rel/case4.toml",
        ],
        "mrclam6": [
            "run",
            str(data / "mrclam" / "MRCLAM_Dataset6"),
            "--config",
            "configs/mrclam/dataset6.toml",
            "--methods",
            "pf",
            "--warmup",
            "30",
        ],
    }
    for seed in range(5):
        table[f"shortbag_seed{seed}"] = [*shortbag, "--seed", str(seed)]
    return table


def _problem(path: Path, text: str, name: str) -> str | None:
    begin, end = markers(name)
    i, j = text.find(begin), text.find(end)
    return f"{path} has no {begin} ... {end} section" if i < 0 or j < i else None
