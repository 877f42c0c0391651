"""``relloc run`` on the shared TIERS recordings: the acceptance bounds of the real-data issue.

Every test reads ``../shared/data`` and skips with the reason when it is absent. The filter
parameters are the library defaults for every bag (no per-bag tuning); the particles start
from the uniform prior over the arena.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from relloc.cli import main
from relloc.config import TeamConfig
from relloc.evaluation.report import ScenarioReport
from relloc.runs.recording import RunOptions, run_recording

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "tiers"


def _run(
    shared_data: Path, name: str, seed: int, warmup: float, methods=("pf", "multilateration")
) -> ScenarioReport:
    bag = shared_data / "tiers" / name
    config = TeamConfig.load(CONFIGS / f"{name}.toml")
    return run_recording(
        bag, config, RunOptions(methods=methods, seed=seed, warmup=warmup, progress=False)
    )


def test_shortbag_default_seed_meets_bounds(shared_data: Path) -> None:
    report = _run(shared_data, "multi4_shortbag_20221011", seed=0, warmup=5.0)
    pf = report.methods["pf"]
    assert set(pf.robots) == {"turtle01", "turtle03", "turtle05"}
    for robot, stats in pf.robots.items():
        assert stats.n > 80, robot
        assert stats.median <= 0.20, (robot, stats.median)
    # Multilateration keeps its gauge continuous without ground truth, so one rotation fitted
    # over the whole run comes within a few centimetres of the per-step oracle.
    fair, oracle = report.methods["multilateration"], report.methods["multilateration_oracle"]
    assert fair.robots["turtle01"].n > 80
    assert fair.mean_ape_median <= oracle.mean_ape_median + 0.05
    # The PF's mean over robots is no worse than multilateration's (one alignment per
    # run). Seed 0 gives 0.099 against 0.107; over seeds 0-19 the PF's mean lies in 0.08-0.16
    # (median 0.10): the formation's orientation about the reference is what varies (docs/explanation/measurements.md).
    assert pf.mean_ape_median <= fair.mean_ape_median, (pf.mean_ape_median, fair.mean_ape_median)


@pytest.mark.slow
def test_shortbag_median_over_seeds_meets_bound(shared_data: Path) -> None:
    medians, means = [], []
    fair = None
    for seed in range(5):
        methods = ("pf", "multilateration") if seed == 0 else ("pf",)
        report = _run(
            shared_data, "multi4_shortbag_20221011", seed=seed, warmup=5.0, methods=methods
        )
        if seed == 0:
            fair = report.methods["multilateration"].mean_ape_median
        pf = report.methods["pf"]
        medians.append([pf.robots[r].median for r in sorted(pf.robots)])
        means.append(pf.mean_ape_median)
    per_robot = np.median(np.array(medians), axis=0)
    assert np.all(per_robot <= 0.20), per_robot
    assert fair is not None and np.median(means) <= fair, (means, fair)


def test_single_range_bag_meets_bound_and_multilateration_has_no_estimate(
    shared_data: Path,
) -> None:
    report = _run(shared_data, "pair_range_20220907_1725", seed=0, warmup=10.0)
    stats = report.methods["pf"].robots["turtle01"]
    assert stats.n > 200
    assert stats.median <= 0.20
    assert report.methods["multilateration"].robots["turtle01"].n == 0


def test_static_pair_covariance_covers_the_unobservable_bearing(shared_data: Path) -> None:
    """One range between two static robots fixes a ring, not a point: the published
    covariance must say so (the error lies inside the 95 % ellipse)."""
    report = _run(shared_data, "pair_chair_moving_20220923", seed=0, warmup=5.0, methods=("pf",))
    p = report.methods["pf"].paired["turtle01"]
    assert len(p.t) > 100
    inside = []
    for err, std in zip(p.est - p.gt, p.std, strict=True):
        inside.append(np.linalg.norm(err) <= 2.45 * std)
    assert np.mean(inside) >= 0.95
    assert np.median(p.std) > 0.5  # wide: the bearing is not known


def test_run_cli_writes_json_with_demo_schema(shared_data: Path, tmp_path: Path) -> None:
    out = tmp_path / "run.json"
    bag = shared_data / "tiers" / "pair_range_20220907_1725"
    rc = main(
        [
            "run",
            str(bag),
            "--config",
            str(CONFIGS / "pair_range_20220907_1725.toml"),
            "--particles",
            "5000",
            "--warmup",
            "10",
            "--json",
            str(out),
            "--out",
            str(tmp_path / "plots"),
            "--no-progress",
        ]
    )
    assert rc == 0
    data = json.loads(out.read_text())
    methods = data["scenarios"]["pair_range_20220907_1725"]["methods"]
    assert methods["pf"]["robots"]["turtle01"]["ape_median"] < 0.3
    assert "mean_ape_median" in methods["pf"]
    assert "multilateration_oracle" in methods
    assert (tmp_path / "plots" / "tum" / "pf_turtle01.txt").read_text().startswith("# timestamp")


def test_run_cli_reports_a_corrupted_bag_clearly(shared_data: Path, tmp_path: Path, capsys) -> None:
    src = shared_data / "tiers" / "pair_range_20220907_1725"
    bag = tmp_path / "broken"
    shutil.copytree(src, bag)
    db = next(bag.glob("*.db3"))
    db.write_bytes(db.read_bytes()[:4096] + b"\x00garbage" * 100)
    rc = main(
        [
            "run",
            str(bag),
            "--config",
            str(CONFIGS / "pair_range_20220907_1725.toml"),
            "--no-progress",
        ]
    )
    assert rc == 2
    err = capsys.readouterr().err
    assert "error" in err and "Traceback" not in err


def test_run_cli_reports_a_missing_topic_clearly(shared_data: Path, tmp_path: Path, capsys) -> None:
    config = TeamConfig.load(CONFIGS / "pair_range_20220907_1725.toml")
    config = config.with_robot("turtle01", odom_topic="/turtle01/no_such_odom")
    path = tmp_path / "team.toml"
    config.save(path)
    rc = main(
        [
            "run",
            str(shared_data / "tiers" / "pair_range_20220907_1725"),
            "--config",
            str(path),
            "--no-progress",
        ]
    )
    assert rc == 2
    err = capsys.readouterr().err
    assert "/turtle01/no_such_odom" in err
