"""The source table: what a path names, the protocol every source follows, the commands' errors."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest
from test_rosbag_source import synthetic_messages, synthetic_team
from test_sightings import _write_dataset

from relloc.cli import main
from relloc.config import RobotConfig, TeamConfig
from relloc.evaluation.report import make_console
from relloc.runs.demo import DemoOptions, run_scenario
from relloc.runs.recording import RunOptions, run_recording
from relloc.sources.protocol import Source
from relloc.sources.table import SourceError, open_source, source_kind


def _describe(source: Source) -> tuple[str, float, int, bool]:
    events = list(source)
    assert [e.t for e in events] == sorted(e.t for e in events)
    assert isinstance(source.stats.as_dict(), dict) and isinstance(source.warnings, list)
    return source.name, round(source.duration, 3), len(events), source.initial_poses() is not None


def test_each_kind_of_path_opens_its_source(
    tmp_path: Path, bag_writer: Callable[..., Path]
) -> None:
    bag = bag_writer(tmp_path / "synthetic", synthetic_messages())
    mcap = bag_writer(tmp_path / "as_mcap", synthetic_messages(), storage="mcap")
    folder = tmp_path / "MRCLAM_Test"
    _write_dataset(folder)
    team = synthetic_team()
    mrclam_team = TeamConfig((RobotConfig("robot1"), RobotConfig("robot2")), "robot1")
    assert [source_kind(p).name for p in (bag, next(mcap.glob("*.mcap")), folder, "single")] == [
        "rosbag2",
        "rosbag2",
        "mrclam",
        "scenario",
    ]
    name, _, n, oracle = _describe(open_source(bag, team))
    assert (name, oracle) == ("synthetic", False) and n > 0
    assert _describe(open_source(folder, mrclam_team)) == ("MRCLAM_Test", 3.0, 12, True)
    name, duration, n, oracle = _describe(open_source("single", None))
    assert (name, duration, oracle) == ("single", 45.0, True) and n > 1000


def test_what_is_no_source_is_one_clear_line(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("")
    for path, problem in (
        (tmp_path / "absent", "not found"),
        (tmp_path / "notes.txt", "not a source"),
    ):
        with pytest.raises(
            SourceError, match=f"{problem}; give a rosbag2 recording .* or a simulated scenario"
        ) as info:
            source_kind(path)
        assert "\n" not in str(info.value)
    folder = tmp_path / "MRCLAM_Test"
    _write_dataset(folder)
    with pytest.raises(SourceError, match="is an MRCLAM data set: it needs a team config"):
        open_source(folder, None)
    (tmp_path / "multi").mkdir()  # an existing path is never a scenario's name
    with pytest.raises(SourceError, match="not a source"):
        source_kind(tmp_path / "multi")


def test_commands_refuse_a_source_they_cannot_use(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "MRCLAM_Test"
    _write_dataset(folder)
    config = tmp_path / "team.toml"
    synthetic_team().save(config)
    assert main(["replay", str(folder), "--config", str(config)]) == 2
    assert (
        "is an MRCLAM data set: relloc replay publishes the ROS 2 messages of a rosbag2"
        in capsys.readouterr().err
    )
    assert main(["calibrate", "single", "--config", str(config)]) == 2
    assert (
        "single is a simulated scenario: calibration needs UWB ranges with motion capture"
        in capsys.readouterr().err
    )
    assert (
        main(
            [
                "run",
                str(tmp_path / "absent"),
                "--config",
                str(config),
                "--out",
                str(tmp_path / "o"),
                "--no-progress",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "relloc run: error: " in err and "absent: not found; give a rosbag2 recording" in err
    assert (
        main(
            [
                "run",
                "single",
                "--config",
                str(config),
                "--out",
                str(tmp_path / "o"),
                "--no-progress",
            ]
        )
        == 2
    )
    assert "brings its own team config: leave out --config" in capsys.readouterr().err


def test_a_scenario_run_gives_the_demos_figures(tmp_path: Path) -> None:
    """``relloc run single`` is the demo's ``single`` scenario: same simulation, same config."""
    console = make_console()
    demo = run_scenario(
        "single", DemoOptions(particles=500, methods=("pf",), progress=False), console
    )
    run = run_recording(
        Path("single"),
        None,
        RunOptions(
            methods=("pf",),
            particles=500,
            warmup=10.0,
            progress=False,
            json_path=tmp_path / "run.json",
        ),
        console,
    )
    assert run.truth_name == "ground truth"
    strip = {"compute_s"}
    as_run = json.loads((tmp_path / "run.json").read_text())["scenarios"]["single"]
    ours = {k: v for k, v in as_run["methods"]["pf"].items() if k not in strip}
    theirs = {k: v for k, v in demo.to_json()["methods"]["pf"].items() if k not in strip}
    assert ours == theirs
    assert ours["robots"]["r1"]["n"] > 250
    assert as_run["source"]["events"]["range"] > 100
