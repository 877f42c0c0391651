"""The command line as a careless user meets it: help for everything, defaults that lose no work,
bad input caught before a run, one error format.

Fast: tiny configs, a 3 s synthetic bag (``test_rosbag_source``) and small CSVs; no shared data.
"""

from __future__ import annotations

import argparse
import time
import tomllib
from collections.abc import Callable
from pathlib import Path

import pytest
from test_rosbag_source import synthetic_messages, synthetic_team

from relloc.cli import _every_parser, build_parser, main
from relloc.cli.common import format_stamp
from relloc.config import ConfigError, TeamConfig, UwbConfig
from relloc.runs.rejections import REASONS, rejection_lines


def _code(args: list[str]) -> int:
    try:
        return main(args)
    except SystemExit as exc:  # argparse's usage errors
        return int(exc.code or 0)


# ---------------------------------------------------------------------------- help
def _subcommand_parsers() -> list[argparse.ArgumentParser]:
    return _every_parser(build_parser())[1:]


def test_every_command_has_a_description() -> None:
    parsers = _subcommand_parsers()
    assert {"relloc demo", "relloc run", "relloc calibrate", "relloc serve"} <= {
        p.prog for p in parsers
    }
    for p in parsers:
        assert p.description and len(p.description) > 30, p.prog


def test_every_option_has_help_and_says_its_default() -> None:
    checked = 0
    for p in _subcommand_parsers():
        formatter = p._get_formatter()
        for action in p._actions:
            if isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
                continue
            assert action.help, (p.prog, action.option_strings or action.dest)
            has_value = (
                action.option_strings
                and not any(action.default is v for v in (None, False, True))
                and action.default != []
            )
            if has_value:
                text = formatter._get_help_string(action) % {"default": action.default}
                assert "default" in text, (p.prog, action.option_strings, text)
            checked += 1
    assert checked > 100


def test_methods_help_lists_every_method() -> None:
    from relloc.methods import METHODS

    run = next(p for p in _subcommand_parsers() if p.prog == "relloc run")
    text = run.format_help()
    for method in METHODS:
        assert method in text


def test_no_command_prints_the_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: relloc") and "calibrate" in out and "serve" in out


# ---------------------------------------------------------------------------- argument checks
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["demo", "--warmup", "-3"],
            "relloc demo: error: argument --warmup: must be a finite number >= 0",
        ),
        (
            ["run", "bag", "--config", "c.toml", "--warmup", "-3"],
            "relloc run: error: argument --warmup",
        ),
        (
            ["demo", "--scenarios", "single", "--warmup", "1000", "--no-progress"],
            "relloc demo: error: --warmup 1000 s is not shorter than single (45.0 s)",
        ),
        (["ranging", "eval", "absent.csv", "--models", "absent"], "relloc ranging: error: "),
    ],
)
def test_bad_arguments_fail_before_the_run_in_one_format(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _code(args) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_unwritable_out_fails_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert (
        _code(["demo", "--scenarios", "single", "--out", str(blocker / "plots"), "--no-progress"])
        == 2
    )
    assert "relloc demo: error: cannot write to --out" in capsys.readouterr().err
    assert (
        _code(["demo", "--scenarios", "single", "--json", str(blocker / "d.json"), "--no-progress"])
        == 2
    )
    assert "cannot write to --json" in capsys.readouterr().err
    config = tmp_path / "team.toml"
    synthetic_team().save(config)
    assert _code(["run", "absent_bag", "--config", str(config), "--out", str(blocker / "o")]) == 2
    assert "relloc run: error: cannot write to --out" in capsys.readouterr().err


def test_config_error_names_the_key(tmp_path: Path) -> None:
    path = tmp_path / "team.toml"
    path.write_text('area = "big"\n[[robots]]\nname = "a"\n[[robots]]\nname = "b"\n')
    with pytest.raises(ConfigError, match=r"area must be four numbers .* got 'big'"):
        TeamConfig.load(path)
    path.write_text('area = [0, 1, 2]\n[[robots]]\nname = "a"\n[[robots]]\nname = "b"\n')
    with pytest.raises(ConfigError, match=r"area must be four numbers"):
        TeamConfig.load(path)


# ---------------------------------------------------------------------------- relloc run
@pytest.fixture
def synthetic_run(tmp_path: Path, bag_writer: Callable[..., Path]) -> tuple[Path, Path]:
    bag = bag_writer(tmp_path / "synthetic", synthetic_messages())
    config = tmp_path / "team.toml"
    synthetic_team().with_filter(particles=300).save(config)
    return bag, config


def test_run_writes_to_out_recording_by_default(
    synthetic_run: tuple[Path, Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    bag, config = synthetic_run
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert (
        main(
            [
                "run",
                str(bag),
                "--config",
                str(config),
                "--methods",
                "pf",
                "--warmup",
                "0.5",
                "--no-progress",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    folder = work / "out" / "synthetic"
    assert (folder / "synthetic_trajectories.png").stat().st_size > 5_000
    assert (folder / "synthetic_ape_time.png").stat().st_size > 5_000
    assert "written to out/synthetic/" in out
    # r3 carries n_9, which no range topic of the bag has: said before the table
    warning = out.index("r3: uwb_node 'n_9' matches no range topic")
    assert warning < out.index("APE after 0.5 s warm-up")
    # the source's rejections as sentences: one NaN and one negative range
    assert (
        "the source dropped 1 UWB ranges that were NaN or infinite [range_nonfinite]: harmless"
        in out
    )
    assert "the source dropped 1 UWB ranges of zero or less [range_nonpositive]: harmless" in out


def test_run_without_any_team_range_is_an_error_before_the_run(
    tmp_path: Path, bag_writer: Callable[..., Path], capsys: pytest.CaptureFixture[str]
) -> None:
    bag = bag_writer(tmp_path / "synthetic", synthetic_messages())
    config = tmp_path / "team.toml"
    synthetic_team(uwb=UwbConfig(range_topic="/other/{a}/{b}/distance")).save(config)
    out = tmp_path / "plots"
    assert (
        main(
            [
                "run",
                str(bag),
                "--config",
                str(config),
                "--out",
                str(out),
                "--warmup",
                "0",
                "--no-progress",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "relloc run: error: no UWB range topic of the bag joins two of the team's nodes" in err


def test_run_warmup_longer_than_the_bag_is_an_error(
    synthetic_run: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag, config = synthetic_run
    args = [
        "run",
        str(bag),
        "--config",
        str(config),
        "--warmup",
        "1000",
        "--out",
        str(tmp_path / "o"),
    ]
    assert main([*args, "--no-progress"]) == 2
    assert "--warmup 1000 s is not shorter than synthetic (3.0 s)" in capsys.readouterr().err


# ---------------------------------------------------------------------------- relloc calibrate
TEAM_TOML = """\
# A hand-written team: every comment must survive calibration.
name = "hand"
reference = "r3"

[[robots]]
name = "r1"
uwb_node = "n_7"           # robot 1 of the CSV

[[robots]]
name = "r3"
uwb_node = "n_3"

[[robots]]
name = "r4"
uwb_node = "n_4"

# Biases from another session; sigmas deliberately unset (the filter's noise model applies).
[uwb]
[uwb.pairs."n_3-n_7"]
bias = 0.1                 # sigma 0.200
source = "old"
"""


def _write_csv(path: Path) -> Path:
    """Pair 1-3 (n_3-n_7) measures 0.5 m long, pair 3-4 (n_3-n_4) 0.25 m (median errors)."""
    rows = ["timestamp,node1,node2,uwb_range,mocap_range,tb_node1_yaw,tb_node2_yaw,error"]
    for k, r in enumerate([1.3, 1.5, 1.7]):
        rows.append(f"{k},1.0,3.0,{r},1.0,0,0,{r - 1.0}")
        rows.append(f"{k},3.0,4.0,{2.2 + 0.05 * k},2.0,0,0,{0.2 + 0.05 * k}")
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.fixture
def team_files(tmp_path: Path) -> tuple[Path, Path]:
    config = tmp_path / "team.toml"
    config.write_text(TEAM_TOML)
    return _write_csv(tmp_path / "errors.csv"), config


def test_calibrate_writes_nothing_unasked(
    team_files: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    csv, config = team_files
    assert main(["calibrate", str(csv), "--config", str(config)]) == 0
    assert config.read_text() == TEAM_TOML
    captured = capsys.readouterr()
    section = tomllib.loads(captured.out)
    assert section["uwb"]["pairs"]["n_3-n_7"] == {"bias": 0.5, "source": "errors"}
    assert section["uwb"]["pairs"]["n_3-n_4"] == {"bias": 0.25, "source": "errors"}
    assert "--in-place" in captured.err and "--write FILE" in captured.err


def test_calibrate_in_place_keeps_comments_and_adds_no_sigma(team_files: tuple[Path, Path]) -> None:
    csv, config = team_files
    assert main(["calibrate", str(csv), "--config", str(config), "--in-place"]) == 0
    text = config.read_text()
    for line in TEAM_TOML.splitlines():
        if line.startswith("#") or "# robot 1 of the CSV" in line:
            assert line in text
    data = tomllib.loads(text)
    pairs = data["uwb"]["pairs"]
    assert pairs["n_3-n_7"] == {"bias": 0.5, "source": "errors"}
    assert pairs["n_3-n_4"] == {"bias": 0.25, "source": "errors"}
    assert "sigma =" not in text
    assert (
        "bias = 0.5                 # sigma 0.296" in text
    )  # the robust sigma (1.4826 MAD), as a note
    assert "bias = 0.25  # sigma 0.074" in text
    assert TeamConfig.load(config).uwb.pairs["n_3-n_7"].sigma is None


def test_calibrate_write_leaves_the_config_and_updates_a_set_sigma(
    team_files: tuple[Path, Path], tmp_path: Path
) -> None:
    csv, config = team_files
    config.write_text(TEAM_TOML.replace('source = "old"', 'sigma = 0.3\nsource = "old"'))
    before = config.read_text()
    copy = tmp_path / "calibrated.toml"
    assert main(["calibrate", str(csv), "--config", str(config), "--write", str(copy)]) == 0
    assert config.read_text() == before
    pairs = TeamConfig.load(copy).uwb.pairs
    assert pairs["n_3-n_7"].bias == 0.5 and pairs["n_3-n_7"].sigma == pytest.approx(
        0.2965, abs=1e-4
    )
    assert pairs["n_3-n_4"].sigma is None  # not set before: stays unset


def test_calibrate_in_place_and_write_exclude_each_other(team_files: tuple[Path, Path]) -> None:
    csv, config = team_files
    assert (
        _code(["calibrate", str(csv), "--config", str(config), "--in-place", "--write", "x.toml"])
        == 2
    )
    assert config.read_text() == TEAM_TOML


# ---------------------------------------------------------------------------- output
def test_rejection_lines_say_what_and_whether_it_matters() -> None:
    lines = rejection_lines(
        "pf", {"repeated_range": 539, "time_jump": 2, "late_measurement": 0, "new_reason": 1}
    )
    assert lines == [
        f"pf dropped 539 {REASONS['repeated_range'][0]} [repeated_range]: {REASONS['repeated_range'][1]}",
        f"pf dropped 2 {REASONS['time_jump'][0]} [time_jump]: {REASONS['time_jump'][1]}",
        "pf dropped 1 events [new_reason]: see the log (-v)",
    ]
    assert rejection_lines("source", {}) == []


def test_stamps_are_iso_times_or_simulator_seconds() -> None:
    assert format_stamp(1796140551.69) == "at 2026-12-01T15:55:51.690Z"
    assert format_stamp(12.345) == "at t = 12.35 s"
    assert format_stamp(None) == "never"


def test_serve_summary_in_sentences_and_iso_times(capsys: pytest.CaptureFixture[str]) -> None:
    from relloc.cli.live import _print_summary

    summary = {
        "uptime_s": 12.5,
        "events": 900,
        "engine_errors": 0,
        "source": {"messages": 1000, "rejected": {"decode_error": 2}, "out_of_order": 3},
        "methods": {
            "pf": {
                "estimates": 120,
                "last_estimate_t": 1796140551.69,
                "ess": 800.0,
                "compute_s": 1.5,
                "rejected": {"repeated_range": 539},
            }
        },
    }
    _print_summary(summary)
    out = capsys.readouterr().out
    assert "pf: 120 estimates, last at 2026-12-01T15:55:51.690Z, ESS 800.0" in out
    assert "1796140551" not in out
    assert "source dropped 2 messages that could not be decoded [decode_error]" in out
    assert "pf dropped 539 ranges equal to their pair's previous one [repeated_range]" in out
    assert "{" not in out


def test_a_second_interrupt_exits_at_once_with_130() -> None:
    import os
    import signal

    from relloc.cli.common import stop_on_signals

    with pytest.raises(SystemExit) as info, stop_on_signals() as stop:
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.wait(1.0)
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(100):  # the handler runs between bytecodes of this thread
            time.sleep(0.01)
    assert info.value.code == 130
