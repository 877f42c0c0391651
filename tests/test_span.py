"""A part of a recording (``--span``): calibrate on one half, score on the other."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from relloc.cli import argtypes
from relloc.sources.span import SpanSource, parse_span
from relloc.sources.table import open_source

REPO = Path(__file__).resolve().parents[1]


def test_spans_parse_with_either_end_left_out() -> None:
    assert parse_span("3:7.5") == (3.0, 7.5)
    assert parse_span(":10") == (0.0, 10.0)
    assert parse_span("17:") == (17.0, math.inf)
    for bad, why in (
        ("5", "START:END"),
        ("a:b", "numbers"),
        ("7:3", "0 <= START < END"),
        ("-1:3", "START < END"),
    ):
        with pytest.raises(ValueError, match=why):
            parse_span(bad)
    with pytest.raises(Exception, match="START < END"):
        argtypes.span("4:4")


def test_a_span_keeps_the_events_of_its_window_only() -> None:
    source = open_source("single", None)
    every = [ev.t for ev in source]
    part = SpanSource(source, (10.0, 20.0))
    times = [ev.t for ev in part]
    t0 = source.start_time
    assert part.start_time == t0 + 10.0 and part.duration == 10.0
    assert times and min(times) >= t0 + 10.0 and max(times) < t0 + 20.0
    assert len(times) == sum(1 for t in every if t0 + 10.0 <= t < t0 + 20.0)
    assert (
        part.initial_poses() is None and SpanSource(source, (0.0, 5.0)).initial_poses() is not None
    )
    assert SpanSource(source, (30.0, math.inf)).duration == pytest.approx(source.duration - 30.0)
    with pytest.raises(ValueError, match="after the end"):
        SpanSource(source, (source.duration + 1.0, math.inf))


@pytest.mark.shared_data
@pytest.mark.slow
def test_calibrated_on_the_first_half_run_on_the_second(shared_data: Path, tmp_path: Path) -> None:
    """The static seven-robot team: biases from the first 17 s, the run on the rest."""
    bag = shared_data / "tiers_uwb_rel" / "case4_test1_static"
    if not bag.is_dir():
        pytest.skip(f"{bag} not found (the seven-robot UWB team)")
    team = tmp_path / "team.toml"
    cli = [sys.executable, "-m", "relloc.cli"]
    done = subprocess.run(
        [
            *cli,
            "calibrate",
            str(bag),
            "--config",
            "configs/tiers_uwb_rel/case4.toml",
            "--span",
            ":17",
            "--write",
            str(team),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    text = team.read_text()
    assert text.count("[uwb.pairs.") == 21 and "case4_test1_static" in text
    out = tmp_path / "run.json"
    done = subprocess.run(
        [
            *cli,
            "run",
            str(bag),
            "--config",
            str(team),
            "--span",
            "17:",
            "--methods",
            "multilateration",
            "--no-progress",
            "--json",
            str(out),
            "--out",
            str(tmp_path / "out"),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert "(17.2 s run)" in done.stdout
    import json

    robots = json.loads(out.read_text())["scenarios"]["case4_test1_static"]["methods"][
        "multilateration"
    ]["robots"]
    # Calibrated biases take every robot's multilateration error under 0.08 m (0.11-0.30 m
    # for four robots with the config's zero biases).
    assert max(r["ape_median"] for r in robots.values()) < 0.08
