"""``scripts/paired_seeds.py``: pairing, the score it reads and the seed-independent shortcut,
on run reports written here (no recording is run)."""

from __future__ import annotations

import argparse
import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import ModuleType

import pytest
from load_file import ROOT, load_module

from relloc.cli.argtypes import seeds

SCRIPT = ROOT / "scripts" / "paired_seeds.py"


def _script() -> ModuleType:
    return load_module(SCRIPT, "paired_seeds")


def _report(path: Path, methods: dict[str, float], unobservable: bool = False) -> Path:
    """A ``relloc run --json`` report with one robot whose APE median (or, with an
    unobservable orientation, shape APE median) per method is given."""
    robots = {
        m: {
            "orientation_unobservable_fraction": 1.0 if unobservable else 0.0,
            "robots": {"r1": {"ape_median": 9.0 if unobservable else v, "shape_ape_median": v}},
        }
        for m, v in methods.items()
    }
    path.write_text(json.dumps({"seed": 0, "scenarios": {"rec": {"methods": robots}}}))
    return path


def test_the_score_is_the_shape_ape_where_the_orientation_is_unobservable(tmp_path: Path) -> None:
    ps = _script()
    assert ps._scores(_report(tmp_path / "a.json", {"pf": 0.1}), "pf") == {"r1": 0.1}
    assert ps._scores(_report(tmp_path / "b.json", {"pf": 0.2}, unobservable=True), "pf") == {
        "r1": 0.2
    }


def _args(tmp_path: Path, a_flags: str, b_flags: str, a_env: str = "", b_env: str = "") -> object:
    return type(
        "Args",
        (),
        {
            "a_method": "pf",
            "b_method": "pf_ul",
            "a_flags": a_flags,
            "b_flags": b_flags,
            "a_env": a_env,
            "b_env": b_env,
            "data": tmp_path,
            "work": tmp_path,
        },
    )()


@pytest.mark.parametrize("independent", [True, False])
def test_pairs_seed_by_seed_and_stops_at_two_identical_seeds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, independent: bool
) -> None:
    ps = _script()
    calls: list[tuple[str, tuple[str, ...], int]] = []

    def fake_run(
        data: Path, name: str, flags: str, methods: list[str], seed: int, work: Path, env: str = ""
    ) -> Path:
        calls.append((flags, tuple(methods), seed))
        value = 0.1 if independent else 0.1 + 0.01 * seed
        return _report(tmp_path / f"{seed}.json", {"pf": value, "pf_ul": value + 0.02})

    monkeypatch.setattr(ps, "_run", fake_run)
    with ThreadPoolExecutor(1) as pool:
        a, b, used = ps._paired(
            pool, _args(tmp_path, "--models m", "--models m"), "rec", [0, 1, 2, 3]
        )
    # equal flags: one run per seed carries both methods
    assert all(c[:2] == ("--models m", ("pf", "pf_ul")) for c in calls)
    assert used == ([0, 1] if independent else [0, 1, 2, 3])
    assert [s for _, _, s in calls] == used
    assert [round(x["r1"], 3) for x in b] == [round(x["r1"] + 0.02, 3) for x in a]


def test_variants_differing_in_environment_run_apart(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Equal flags but another environment (the NumPy step against the compiled one): each
    variant is its own run, with its own environment."""
    ps = _script()
    calls: list[tuple[tuple[str, ...], str]] = []

    def fake_run(
        data: Path, name: str, flags: str, methods: list[str], seed: int, work: Path, env: str = ""
    ) -> Path:
        calls.append((tuple(methods), env))
        return _report(tmp_path / f"{seed}{env}.json", {"pf": 0.1 + 0.01 * seed, "pf_ul": 0.2})

    monkeypatch.setattr(ps, "_run", fake_run)
    with ThreadPoolExecutor(1) as pool:
        ps._paired(pool, _args(tmp_path, "", "", "RELLOC_COMPILED=0", ""), "rec", [0, 1, 2])
    assert sorted(set(calls)) == [(("pf",), "RELLOC_COMPILED=0"), (("pf_ul",), "")]
    assert len(calls) == 6


def test_seed_lists_of_the_sweep_scripts() -> None:
    """``--seeds`` of paired_seeds and online_bias_sessions: a range or a list, usage errors
    for the rest, and the table says a range back as a range."""
    assert seeds("0-3") == [0, 1, 2, 3] and seeds("4") == [4] and seeds("1,5,2") == [1, 5, 2]
    for bad in ("3-1", "a", "-1", "1,,2"):
        with pytest.raises(argparse.ArgumentTypeError):
            seeds(bad)
    ps = _script()
    assert ps._label([0, 1, 2]) == "0-2" and ps._label([4]) == "4" and ps._label([1, 5]) == "1,5"
