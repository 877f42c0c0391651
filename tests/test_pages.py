"""relloc.evaluation.pages for the scripts that write tables into pages: ``--page`` and
``--section`` are checked before any work, and the printed table lands between the markers."""

from __future__ import annotations

from pathlib import Path

import pytest

from relloc.evaluation.pages import check_page_args, markers, print_table


def test_page_args_are_checked_before_the_work_and_the_table_lands_between_markers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    page = tmp_path / "page.md"
    begin, end = markers("t")
    page.write_text(f"intro\n{begin}\nold\n{end}\nafter\n")
    check_page_args(None, None)
    check_page_args(page, "t")
    with pytest.raises(SystemExit, match="go together"):
        check_page_args(page, None)
    with pytest.raises(SystemExit, match="go together"):
        check_page_args(None, "t")
    with pytest.raises(SystemExit, match="no <!-- u figures: begin -->"):
        check_page_args(page, "u")
    print_table(["| a |", "|---|"], page, "t")
    assert capsys.readouterr().out == "| a |\n|---|\n"
    assert page.read_text() == f"intro\n{begin}\n| a |\n|---|\n{end}\nafter\n"
    print_table(["| b |"], None, None)
    assert capsys.readouterr().out == "| b |\n" and "| b |" not in page.read_text()
