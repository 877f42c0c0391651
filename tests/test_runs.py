"""The public run API (:mod:`relloc.runs`): the sweep helper runs ``relloc`` jobs and collects their JSON."""

from __future__ import annotations

from pathlib import Path

import pytest

from relloc.runs import SweepError, SweepJob, run_jobs, sweep

QUICK = ("demo", "--scenarios", "single", "--methods", "multilateration", "--no-progress")
"""The fastest simulated run (about two seconds)."""


def test_a_sweep_returns_each_jobs_json_in_order(tmp_path: Path) -> None:
    jobs = [SweepJob((*QUICK, "--seed", str(seed)), tmp_path / f"s{seed}.json") for seed in (0, 1)]
    payloads = sweep(jobs, workers=2)
    assert [p["seed"] for p in payloads] == [0, 1]
    assert all("multilateration" in p["scenarios"]["single"]["methods"] for p in payloads)
    assert all(job.json_path.is_file() for job in jobs)


def test_a_failed_job_is_named_with_its_error(tmp_path: Path) -> None:
    good = SweepJob(QUICK, tmp_path / "good.json")
    bad = SweepJob((*QUICK, "--warmup", "1000"), tmp_path / "bad.json", name="too-long-warmup")
    with pytest.raises(SweepError) as raised:
        sweep([good, bad], workers=2)
    message = str(raised.value)
    assert "too-long-warmup failed (exit 2)" in message
    assert "--warmup 1000 s is not shorter than single" in message  # the job's stderr tail
    assert raised.value.result.job is bad
    results = run_jobs([good, bad], workers=1)
    assert results[0].ok and results[0].error is None and results[0].wall_s > 0
    assert not results[1].ok and results[1].returncode == 2
    assert "not shorter" in results[1].last_line()
