"""Damaged MRCLAM input: malformed rows skipped and counted by file, line and reason; a missing
or empty file one line naming it; never a traceback."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_sightings import _write_dataset

from relloc.cli import main
from relloc.config import RobotConfig, TeamConfig
from relloc.events import SightingEvent
from relloc.sources.mrclam import MalformedRow, MrclamError, MrclamSource, read_table

GARBAGE = (
    "garbage \t 14 \t 2.0 \t 0.1",
    "1248444200.0 \t 14",
    "nan \t 14 \t 2.0 \t 0.1",
    "1248444200.0 \t 14 \t inf \t 0.1",
    "1.0 2.0 3.0 4.0 5.0",
)
"""The kinds of bad row: text, too few columns, NaN, infinity, too many columns."""
REASONS = ("text", "columns", "nonfinite", "nonfinite", "columns")


def _damage_measurements(path: Path, count: int) -> list[MalformedRow]:
    """``count`` garbage rows scattered through ``path``; the rows it now holds that are bad."""
    lines = path.read_text().splitlines()
    data = [k for k, line in enumerate(lines) if line.strip() and not line.startswith("#")]
    at = set(np.linspace(data[0], data[-1], count).astype(int).tolist())
    assert len(at) == count
    out, bad = [], []
    for k, line in enumerate(lines):
        if k in at:
            kind = len(bad) % len(GARBAGE)
            out.append(GARBAGE[kind])
            bad.append(MalformedRow(path.name, len(out), REASONS[kind]))
        out.append(line)
    path.write_text("\n".join(out) + "\n")
    return bad


def _truncate(path: Path, fraction: float) -> int:
    """Cut ``path`` off in the middle of a line (after its second field): the line number."""
    text = path.read_text()
    start = text.index("\n", int(len(text) * fraction)) + 1
    second_tab = text.index("\t", text.index("\t", start) + 1)
    path.write_text(text[:second_tab])
    return text[:start].count("\n") + 1


def _team(*names: str) -> TeamConfig:
    return TeamConfig(tuple(RobotConfig(n) for n in names), names[0])


def test_garbage_rows_and_a_truncated_odometry_file_in_dataset_6(
    shared_data: Path, tmp_path: Path
) -> None:
    clean = shared_data / "mrclam" / "MRCLAM_Dataset6"
    if not (clean / "Barcodes.dat").is_file():
        pytest.skip(f"{clean} not found")
    folder = tmp_path / "MRCLAM_Damaged"
    folder.mkdir()
    for f in clean.iterdir():
        if f.name in ("Robot3_Measurement.dat", "Robot1_Odometry.dat"):
            shutil.copyfile(f, folder / f.name)
        else:
            (folder / f.name).symlink_to(f)
    bad = _damage_measurements(folder / "Robot3_Measurement.dat", 50)
    cut = _truncate(folder / "Robot1_Odometry.dat", 0.6)
    team = _team("robot1", "robot2", "robot3", "robot4", "robot5")
    source = MrclamSource(folder, team)
    assert source.malformed == [MalformedRow("Robot1_Odometry.dat", cut, "columns"), *bad]
    assert source.stats.rejected == {"malformed_row": 51}
    assert (
        source.warnings[0] == f"Robot1_Odometry.dat: 1 malformed rows skipped: line {cut} (columns)"
    )
    assert source.warnings[1].startswith("Robot3_Measurement.dat: 50 malformed rows skipped: line ")
    assert source.warnings[1].endswith(" and 45 more")
    # every good row is read as from the clean file: the sightings of robot3 are the same
    assert np.array_equal(source.measurements[3], read_table(clean / "Robot3_Measurement.dat", 4))
    odometry = read_table(clean / "Robot1_Odometry.dat", 3)
    assert np.array_equal(source.odometry[1], odometry[: len(source.odometry[1])])
    assert len(source.odometry[1]) == cut - 5  # four header lines, the cut line itself
    sightings = [e for e in source._sightings(3) if isinstance(e, SightingEvent)]
    assert len(sightings) == source.stats.counts["sightings"] > 0
    # The team the source runs says where each robot's odometry comes from (robots with
    # odometry are not ranges-only robots to the filter's automatic choice).
    assert [r.odom_topic for r in source.config.robots][:2] == [
        "Robot1_Odometry.dat",
        "Robot2_Odometry.dat",
    ]


def test_a_run_over_damaged_files_counts_the_rows(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "MRCLAM_Test"
    _write_dataset(folder)
    bad = _damage_measurements(folder / "Robot1_Measurement.dat", 2)
    with (folder / "Robot2_Odometry.dat").open("a") as f:
        f.write("103.5 \t 0.0")  # cut off mid-line, no newline
    config = tmp_path / "team.toml"
    _team("robot1", "robot2").save(config)
    json_path = tmp_path / "run.json"
    argv = [
        "run",
        str(folder),
        "--config",
        str(config),
        "--methods",
        "multilateration",
        "--warmup",
        "0",
        "--out",
        str(tmp_path / "o"),
        "--json",
        str(json_path),
        "--no-progress",
    ]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert (
        f"Robot1_Measurement.dat: 2 malformed rows skipped: line {bad[0].line} (text), line {bad[1].line} (columns)"
        in out
    )
    assert "Robot2_Odometry.dat: 1 malformed rows skipped: line 5 (columns)" in out
    assert "malformed_row" in out
    assert (
        json.loads(json_path.read_text())["scenarios"]["MRCLAM_Test"]["source"][
            "rejected_malformed_row"
        ]
        == 3
    )


@pytest.mark.parametrize("damage", ["missing", "empty", "comments only", "all malformed"])
def test_a_missing_or_empty_file_is_one_line_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], damage: str
) -> None:
    folder = tmp_path / "MRCLAM_Test"
    _write_dataset(folder)
    path = folder / "Robot2_Measurement.dat"
    if damage == "missing":
        path.unlink()
    else:
        path.write_text(
            {"empty": "", "comments only": "# a header\n", "all malformed": "x y\n1 2 3\n"}[damage]
        )
    with pytest.raises(MrclamError, match=r"Robot2_Measurement\.dat"):
        MrclamSource(folder, _team("robot1", "robot2"))
    config = tmp_path / "team.toml"
    _team("robot1", "robot2").save(config)
    assert (
        main(
            [
                "run",
                str(folder),
                "--config",
                str(config),
                "--warmup",
                "0",
                "--no-progress",
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "Robot2_Measurement.dat" in err and "Traceback" not in err and len(err.splitlines()) == 1


def test_without_a_list_a_malformed_row_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "t.dat"
    path.write_text("# h\n1 2 3\n4 five 6\n")
    with pytest.raises(MrclamError, match="line 3 is malformed \\(text\\)"):
        read_table(path, 3)
    skipped: list[MalformedRow] = []
    assert read_table(path, 3, skipped).tolist() == [[1.0, 2.0, 3.0]]
    assert skipped == [MalformedRow("t.dat", 3, "text")]
