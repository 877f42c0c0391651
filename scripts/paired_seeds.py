"""Two variants of ``relloc run`` on the shared recordings, paired seed by seed.

One seed of a 17 s recording says little: on the shortbag the APE median of one robot moves
by 0.05-0.1 m from seed to seed with everything else fixed. This runs variant A and variant B
(a method and extra ``relloc run`` flags each) on the same seeds, pairs each seed's B with its
A, and prints per robot the means, the mean difference with its standard error, the worst
seed and how many seeds keep B within ``--bound`` of A. The score is the APE median, or the
shape APE median where the formation's orientation is unobservable (two parked robots, the
static team without odometry).

    PYTHONPATH=src .venv/bin/python scripts/paired_seeds.py --seeds 0-19 --b-flags "--bias online"
    M="--models out/models/stacked"; PYTHONPATH=src .venv/bin/python scripts/paired_seeds.py \
        --seeds 0-19 --b-method pf_ul --a-flags "$M" --b-flags "$M" --bound 0.01

``--a-env``/``--b-env KEY=VALUE`` set a variant's environment (``RELLOC_COMPILED=0``: the
particle filter's NumPy step). ``--recordings`` takes the UWB recordings unless told;
``MRCLAM_Dataset6`` (no UWB) is run only when named. Equal flags and environments run both
methods in one ``relloc run``. Runs go in ``--jobs`` processes (one numpy thread each); every
run's JSON stays under ``--work`` and is reused (keyed by flags and methods
only: empty it after changing the code or the models); a recording whose first two seeds agree
exactly in both variants (the smoother draws no random numbers) is not run on the others. ``--page FILE --section NAME`` writes the table between the page's markers
(``relloc.evaluation.pages``): docs/explanation/self-calibration.md, docs/explanation/range-correction.md.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import shlex
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from relloc.cli import argtypes
from relloc.evaluation.pages import check_page_args, print_table
from relloc.runs.sweep import SweepJob, run_job

RECORDINGS = {
    # name: (folder under --data, config, warm-up in s)
    "multi4_shortbag_20221011": (
        "tiers/multi4_shortbag_20221011",
        "configs/tiers/multi4_shortbag_20221011.toml",
        5.0,
    ),
    "pair_range_20220907_1725": (
        "tiers/pair_range_20220907_1725",
        "configs/tiers/pair_range_20220907_1725.toml",
        10.0,
    ),
    "pair_chair_moving_20220923": (
        "tiers/pair_chair_moving_20220923",
        "configs/tiers/pair_chair_moving_20220923.toml",
        10.0,
    ),
    "case4_test1_static": (
        "tiers_uwb_rel/case4_test1_static",
        "configs/tiers_uwb_rel/case4.toml",
        5.0,
    ),
    "MRCLAM_Dataset6": ("mrclam/MRCLAM_Dataset6", "configs/mrclam/dataset6.toml", 30.0),
}
"""The shared recordings and their warm-up windows (those of the results pages): the UWB teams
and the MRCLAM session (camera sightings of teammates, no UWB; about a minute a run)."""
UWB_RECORDINGS = [name for name in RECORDINGS if not name.startswith("MRCLAM")]
"""What ``--recordings`` runs unless told: the recordings with UWB ranges."""


def _label(seeds: list[int]) -> str:
    """``seeds`` as the command line says them: ``LO-HI`` when consecutive."""
    if len(seeds) > 1 and seeds == list(range(seeds[0], seeds[-1] + 1)):
        return f"{seeds[0]}-{seeds[-1]}"
    return ",".join(map(str, seeds))


ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""Each run on one core: ``--jobs`` runs at once share the machine."""


def _env(text: str) -> dict[str, str]:
    """``KEY=VALUE ...`` as a mapping (a variant's ``--a-env``/``--b-env``)."""
    pairs = [item.partition("=") for item in shlex.split(text)]
    if any(not sep or not key for key, sep, _ in pairs):
        raise SystemExit(f"--a-env/--b-env take KEY=VALUE words, not {text!r}")
    return {key: value for key, _, value in pairs}


def _run(
    data: Path, name: str, flags: str, methods: list[str], seed: int, work: Path, env: str = ""
) -> Path:
    folder, config, warmup = RECORDINGS[name]
    tag = f"{flags}|{','.join(methods)}" + (f"|{env}" if env else "")
    key = hashlib.sha1(tag.encode()).hexdigest()[:10]
    out = work / name / f"{key}_s{seed}.json"
    if out.exists():
        return out
    job = SweepJob(
        [
            "run",
            str(data / folder),
            "--config",
            config,
            "--methods",
            ",".join(methods),
            "--warmup",
            str(warmup),
            "--seed",
            str(seed),
            "--no-progress",
            *shlex.split(flags),
        ],
        out,
        env={**ONE_THREAD, **_env(env)},
    )
    result = run_job(job)
    if not result.ok:
        raise SystemExit(result.message())
    return out


def _scores(path: Path, method: str) -> dict[str, float]:
    """Per robot the APE median, or the shape APE median where the orientation is unobservable;
    robots without a score (the reference) left out."""
    scenario = next(iter(json.loads(path.read_text())["scenarios"].values()))
    m = scenario["methods"][method]
    key = (
        "shape_ape_median"
        if (m.get("orientation_unobservable_fraction") or 0.0) > 0.5
        else "ape_median"
    )
    return {r: v[key] for r, v in m["robots"].items() if v.get(key) is not None}


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--data", type=Path, default=Path("../shared/data"))
    p.add_argument("--recordings", default=",".join(UWB_RECORDINGS), help="comma-separated names")
    p.add_argument(
        "--seeds", type=argtypes.seeds, default="0-19", help="LO-HI or a comma-separated list"
    )
    p.add_argument("--a-method", default="pf")
    p.add_argument("--a-flags", default="")
    p.add_argument("--b-method", default="pf")
    p.add_argument("--b-flags", default="")
    p.add_argument("--a-env", default="", help="KEY=VALUE ... in variant A's environment")
    p.add_argument("--b-env", default="", help="KEY=VALUE ... in variant B's environment")
    p.add_argument("--bound", type=float, default=0.03, help="B may be this much worse than A (m)")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument(
        "--work", type=Path, default=Path("out/paired_seeds"), help="run reports, reused"
    )
    p.add_argument("--page", type=Path, default=None, help="Markdown page to write the table into")
    p.add_argument("--section", default=None, help="the page's section (its markers' name)")
    args = p.parse_args()
    check_page_args(args.page, args.section)
    seeds = args.seeds
    names = args.recordings.split(",")
    lines = [
        f"A: `{f'{args.a_env} {args.a_method} {args.a_flags}'.strip()}`; "
        f"B: `{f'{args.b_env} {args.b_method} {args.b_flags}'.strip()}`"
        + f"; seeds {_label(seeds)} ({len(seeds)}); `scripts/paired_seeds.py`",
        "",
        f"| recording | robot | A mean | B mean | B - A mean +- s.e. | worst seed B - A | seeds with B - A <= {args.bound} |",
        "|---|---|---|---|---|---|---|",
    ]
    with ThreadPoolExecutor(args.jobs) as pool:
        for name in names:
            a, b, used = _paired(pool, args, name, seeds)
            for robot in a[0]:
                va = np.array([x[robot] for x in a])
                vb = np.array([x[robot] for x in b])
                d = vb - va
                se = float(d.std(ddof=1) / math.sqrt(d.size)) if d.size > 1 else float("nan")
                worst = int(np.argmax(d))
                count = (
                    f"{int((d <= args.bound).sum())} of {d.size}"
                    if used == seeds
                    else "all (seed-independent)"
                )
                lines.append(
                    f"| {name} | {robot} | {va.mean():.3f} | {vb.mean():.3f} | {d.mean():+.3f} +- {se:.3f} "
                    f"| {d[worst]:+.3f} (seed {used[worst]}) | {count} |"
                )
    print_table(lines, args.page, args.section)


def _paired(
    pool: ThreadPoolExecutor, args: argparse.Namespace, name: str, seeds: list[int]
) -> tuple[list[dict[str, float]], list[dict[str, float]], list[int]]:
    """Both variants' scores on ``name`` per seed, and the seeds run. A recording whose first
    two seeds give identical scores in both variants (a filter that draws no random numbers,
    such as the smoother) is not run on the rest."""
    same = args.a_flags == args.b_flags and args.a_env == args.b_env
    methods_a = [args.a_method, args.b_method] if same else [args.a_method]

    def scores(batch: list[int]) -> tuple[list[dict[str, float]], list[dict[str, float]]]:
        runs_a = list(
            pool.map(
                lambda s: _run(args.data, name, args.a_flags, methods_a, s, args.work, args.a_env),
                batch,
            )
        )
        runs_b = (
            runs_a
            if same
            else list(
                pool.map(
                    lambda s: _run(
                        args.data, name, args.b_flags, [args.b_method], s, args.work, args.b_env
                    ),
                    batch,
                )
            )
        )
        return [_scores(r, args.a_method) for r in runs_a], [
            _scores(r, args.b_method) for r in runs_b
        ]

    a, b = scores(seeds[:2])
    if len(seeds) > 2 and a[0] == a[1] and b[0] == b[1]:
        return a, b, seeds[:2]
    rest_a, rest_b = scores(seeds[2:])
    return a + rest_a, b + rest_b, seeds


if __name__ == "__main__":
    main()
