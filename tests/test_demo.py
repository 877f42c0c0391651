"""``relloc demo``: the command runs end to end and writes the documented JSON schema; the
filter meets the simulator bounds of the core issue at the default settings (seed 0)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from relloc.cli import main


@pytest.fixture(scope="module")
def demo_json(tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("demo")
    rc = main(
        [
            "demo",
            "--seed",
            "0",
            "--scenarios",
            "multi,single",
            "--out",
            str(out),
            "--json",
            str(out / "demo.json"),
            "--no-progress",
        ]
    )
    assert rc == 0
    for name in (
        "multi_trajectories.png",
        "multi_ape.png",
        "single_trajectories.png",
        "single_ape.png",
    ):
        assert (out / name).stat().st_size > 10_000, name
    return json.loads((out / "demo.json").read_text())


def test_demo_json_schema(demo_json: dict) -> None:
    for scenario in ("multi", "single"):
        methods = demo_json["scenarios"][scenario]["methods"]
        assert {"pf", "multilateration"} <= set(methods)
        for robot in methods["pf"]["robots"].values():
            assert {"ape_median", "ape_rmse", "n"} <= set(robot)


def test_demo_pf_meets_bounds_from_uniform_prior(demo_json: dict) -> None:
    multi = demo_json["scenarios"]["multi"]["methods"]
    for robot, figures in multi["pf"]["robots"].items():
        assert figures["n"] > 300, robot
        assert figures["ape_median"] <= 0.15, (robot, figures)
    assert multi["pf"]["mean_ape_median"] < multi["multilateration"]["mean_ape_median"]
    single = demo_json["scenarios"]["single"]["methods"]
    assert single["pf"]["robots"]["r1"]["ape_median"] <= 0.25
    assert single["multilateration"]["robots"]["r1"]["n"] == 0  # one range: no estimate


def test_unknown_method_is_a_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--methods", "pf,magic", "--no-progress"]) == 2
    assert "unknown method" in capsys.readouterr().err


def test_demo_is_reproducible(tmp_path: Path) -> None:
    figures = []
    for k in range(2):
        path = tmp_path / f"d{k}.json"
        main(
            [
                "demo",
                "--seed",
                "3",
                "--scenarios",
                "single",
                "--particles",
                "2000",
                "--json",
                str(path),
                "--out",
                str(tmp_path / f"o{k}"),
                "--no-progress",
            ]
        )
        figures.append(json.loads(path.read_text())["scenarios"]["single"]["methods"]["pf"])
    assert figures[0]["robots"] == figures[1]["robots"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["demo", "--seed", "-1"], "--seed: must be >= 0"),
        (["demo", "--particles", "0"], "--particles: must be >= 1"),
        (["demo", "--scenarios", "multi,bogus"], "unknown scenario 'bogus'"),
        (
            ["serve", "--config", "x.toml", "--duration", "nan"],
            "--duration: must be a finite number",
        ),
    ],
)
def test_bad_arguments_are_one_line_errors(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    try:
        code = main(args)
    except SystemExit as exc:  # argparse's usage error
        code = exc.code
    assert code == 2
    assert message in capsys.readouterr().err
