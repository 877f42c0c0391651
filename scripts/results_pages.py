"""Rerun the evaluation commands and the cheap benchmarks; write the results page from their JSON.

    .venv/bin/python scripts/results_pages.py                 # make results: docs/results/index.md
    .venv/bin/python scripts/results_pages.py --quick --out /tmp/r.md --generated /tmp/g

The runs are those of ``scripts/figures_check.py`` (``relloc.evaluation.pages.figure_runs``: the
demo, the self-calibration demo, the TIERS shortbag seeds 0-4, ``pair_range`` with calibrated and
online biases, MRCLAM Dataset 6) plus the 10-robot grid; a run whose data is absent is listed as skipped. The benchmarks are
those of ``benchmarks/`` that take seconds (CDR codecs, scaling, adaptive particle count,
ranging inference, TLS cost, and the pfilter comparison where its environment exists). Every
figure on the page is read from a ``--json`` file: nothing is copied by hand.

It also runs the first-run tutorial's command (``make demo``) and writes its printed table and
one of its plots under ``--generated``, which ``docs/tutorials/first-run.md`` includes.
``--quick`` (for the tests) runs the demo's ``single`` scenario alone and tiny benchmarks;
``--from-json`` rewrites the page from an earlier run's JSON without running anything.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import subprocess
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from relloc.evaluation.pages import figure_runs
from relloc.runs.sweep import SweepJob, run_job

ROOT = Path(__file__).resolve().parents[1]
# The first-run tutorial's command, as `make demo` runs it.
FIRST_RUN = ["demo", "--seed", "0", "--out", "out/demo", "--json", "out/demo/demo.json"]
FIRST_RUN_PLOT = "multi_trajectories.png"
# Rich lays tables out to the terminal's width: fixed, so that the page does not depend on it.
COLUMNS = "120"


def _fmt(x: Any, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:.{digits}f}" if isinstance(x, float) else str(x)


def machine() -> str:
    import numpy

    cpu = platform.processor() or platform.machine()
    model = ""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        names = [
            ln.split(":", 1)[1].strip()
            for ln in cpuinfo.read_text().splitlines()
            if ln.startswith("model name")
        ]
        model = names[0] if names else ""
    return (
        f"{model or cpu}, {os.cpu_count()} CPUs, {platform.system()} {platform.release()}, "
        f"Python {platform.python_version()}, NumPy {numpy.__version__}"
    )


# ---------------------------------------------------------------- evaluation runs


def evaluation_runs(data: Path, quick: bool) -> dict[str, list[str]]:
    if quick:
        return {"demo": ["demo", "--seed", "0", "--scenarios", "single"]}
    table = figure_runs(data)
    table["grid10"] = [
        "demo",
        "--scenarios",
        "grid",
        "--robots",
        "10",
        "--particles",
        "20000",
        "--seed",
        "0",
    ]
    return table


def scenario_table(name: str, scenario: dict[str, Any]) -> list[str]:
    nav = scenario.get("navigation")
    if "methods" not in scenario:
        return [
            f"**{name}**: positioning APE median {_fmt((nav or {}).get('ape_median'))} m, "
            f"tracking error median {_fmt((nav or {}).get('tracking_median'))} m.",
            "",
        ]
    out = [
        f"**{name}**: reference `{scenario.get('reference')}`, warm-up "
        f"{_fmt(scenario.get('warmup_s'), 0)} s, {_fmt(scenario.get('duration_s'), 1)} s long.",
        "",
        "| method | robot | APE median (m) | shape APE median (m) | APE RMSE (m) | NEES median "
        "| 95 % coverage |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for method, m in scenario.get("methods", {}).items():
        for robot, r in m.get("robots", {}).items():
            out.append(
                f"| {method} | {robot} | {_fmt(r.get('ape_median'))} | "
                f"{_fmt(r.get('shape_ape_median'))} | "
                f"{_fmt(r.get('ape_rmse'))} | {_fmt(r.get('nees_median'), 2)} | "
                f"{_fmt(r.get('coverage95'), 2)} |"
            )
    if nav:
        out += [
            "",
            f"Navigation: positioning APE median {_fmt(nav.get('ape_median'))} m, tracking "
            f"error median {_fmt(nav.get('tracking_median'))} m.",
        ]
    return [*out, ""]


def run_section(name: str, argv: list[str], json_path: Path, status: str) -> list[str]:
    command = " ".join(["relloc", *argv, "--json", f"{name}.json"])
    out = [f"### {name}", "", "```bash", command, "```", ""]
    if not json_path.exists():
        return [*out, f"Not run: {status}", ""]
    data = json.loads(json_path.read_text())
    for scenario_name, scenario in data.get("scenarios", {}).items():
        out += scenario_table(scenario_name, scenario)
    return out


def _last_line(done: subprocess.CompletedProcess[str]) -> str:
    lines = (done.stderr or done.stdout or "").strip().splitlines()
    return lines[-1] if lines else f"exit {done.returncode}"


def run_one(name: str, argv: list[str], folder: Path) -> str:
    job = SweepJob([*argv, "--no-progress", "--out", str(folder / name)], folder / f"{name}.json")
    result = run_job(job)  # removes an earlier run's JSON first: no stale figures
    return "ok" if result.returncode == 0 else result.last_line()


# ---------------------------------------------------------------- the first-run tutorial


def first_run(generated: Path, quick: bool) -> str:
    """Run the tutorial's command; write what it prints and its trajectory plot under
    ``generated``. Returns "ok" or why not."""
    argv, out = FIRST_RUN, ROOT / "out" / "demo"
    if quick:
        out = generated / "demo"
        argv = [
            "demo",
            "--seed",
            "0",
            "--scenarios",
            "single",
            "--out",
            str(out),
            "--json",
            str(out / "demo.json"),
        ]
    env = {**os.environ, "COLUMNS": COLUMNS, "NO_COLOR": "1"}
    done = subprocess.run(
        [sys.executable, "-m", "relloc.cli", *argv, "--no-progress"],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
    )
    if done.returncode != 0:
        return _last_line(done)
    generated.mkdir(parents=True, exist_ok=True)
    text = "\n".join(line.rstrip() for line in done.stdout.splitlines())
    (generated / "first-run-output.txt").write_text(text + "\n")
    plot = out / FIRST_RUN_PLOT
    if not plot.exists():
        plot = next(iter(sorted(out.glob("*_trajectories.png"))), plot)
    if not plot.exists():
        return "no trajectory plot written"
    shutil.copyfile(plot, generated / "first-run-trajectories.png")
    return "ok"


# ---------------------------------------------------------------- benchmarks


def benchmarks(quick: bool) -> dict[str, list[str]]:
    """The benchmarks that take seconds, with their arguments (tiny ones with ``quick``)."""
    if quick:
        return {
            "cdr_codecs": ["--n", "200", "--rounds", "1"],
            "scaling": [
                "--particles",
                "1000",
                "--robots",
                "2",
                "--reps",
                "2",
                "--copy-mb",
                "8",
                "--hypotheses",
                "1",
            ],
        }
    return {
        "cdr_codecs": ["--n", "5000", "--rounds", "3"],
        "scaling": [],
        "filter_vs_pfilter": [
            "--particles",
            "400",
            "4000",
            "40000",
            "--reps",
            "20",
            "--clock",
            "cpu",
        ],
        "adaptive_particles": ["--seeds", "0", "--repeats", "1"],
        "ranging_inference": ["--untrained", "--n", "500"],
        "tls_cost": ["--messages", "1000", "--rounds", "2"],
    }


def bench_python(name: str) -> Path:
    """pfilter is not a dependency: its comparison runs in `make bench`'s environment."""
    bench = ROOT / ".venv-bench" / "bin" / "python"
    return bench if name == "filter_vs_pfilter" and bench.exists() else Path(sys.executable)


def bench_one(name: str, argv: list[str], folder: Path) -> str:
    json_path = folder / f"{name}.json"
    json_path.unlink(missing_ok=True)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    done = subprocess.run(
        [
            str(bench_python(name)),
            str(ROOT / "benchmarks" / f"{name}.py"),
            *argv,
            "--json",
            str(json_path),
        ],
        capture_output=True,
        text=True,
        env=env,
    )
    if done.returncode == 0:
        return "ok"
    if name == "filter_vs_pfilter" and done.returncode == 2:
        return "pfilter is not installed here (`make bench` makes its environment)."
    return _last_line(done)


def _ms(seconds: float | None) -> str:
    return "–" if seconds is None else f"{seconds * 1e3:.2f} ms"


def cdr_table(d: dict[str, Any]) -> list[str]:
    out = ["| operation | relloc.ros.cdr | rosbags | speed-up |", "| --- | ---: | ---: | ---: |"]
    for op, r in d.items():
        out.append(
            f"| {op} | {r['relloc_us']:.2f} µs | {r['rosbags_us']:.2f} µs | {r['speedup']:.1f}x |"
        )
    return out


def scaling_table(d: dict[str, Any]) -> list[str]:
    out = [
        f"Copy bandwidth {d['bandwidth_bytes_per_s'] / 1e9:.1f} GB/s (read + write).",
        "",
        "| robots | particles | D | K | update | update / pass | update / floor |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for p in [*d.get("particles_sweep", []), *d.get("robots_sweep", [])]:
        out.append(
            f"| {p['robots']} | {p['particles']} | {p['dim']} | {p['pairs']} | "
            f"{_ms(p['update_s'])} | {p['update_over_pass']:.0f} | "
            f"{p['update_over_floor']:.0f} |"
        )
    if d.get("graph_sweep"):
        out += [
            "",
            "The range-graph Gaussian sum (`pf` from 12 robots on), per update:",
            "",
            "| robots | hypotheses | D | K | update |",
            "| ---: | ---: | ---: | ---: | ---: |",
        ]
        out += [
            f"| {g['robots']} | {g['hypotheses']} | {g['dim']} | {g['pairs']} | "
            f"{_ms(g['update_s'])} |"
            for g in d["graph_sweep"]
        ]
    return out


def pfilter_table(d: dict[str, Any]) -> list[str]:
    out = [
        "| particles | relloc / update | pfilter / update | speed-up |",
        "| ---: | ---: | ---: | ---: |",
    ]
    for m, r in d.items():
        out.append(f"| {m} | {_ms(r['relloc_s'])} | {_ms(r['pfilter_s'])} | {r['speedup']:.1f}x |")
    return out


def adaptive_table(d: dict[str, Any]) -> list[str]:
    out = [
        "| case | fixed: particles, ms / update | adaptive: particles, ms / update | "
        "ratio after warm-up | ratio, last seconds |",
        "| --- | --- | --- | ---: | ---: |",
    ]
    for case, r in d.items():
        f, a = r["fixed"], r["adaptive"]
        out.append(
            f"| {case} | {f['count_tail']:.0f}, {f['tail_ms']:.2f} | "
            f"{a['count_tail']:.0f}, {a['tail_ms']:.2f} | {r['ratio_after_warmup']:.2f}x | "
            f"{r['ratio_tail']:.2f}x |"
        )
    return out


def ranging_table(d: dict[str, Any]) -> list[str]:
    out = [
        f"Budget {d['budget_s'] * 1e3:.0f} ms per prediction, on {d['core']}.",
        "",
        "| variant | model alone (median / p90) | engine stage (median / p90) |",
        "| --- | ---: | ---: |",
    ]
    for name, v in d["variants"].items():
        out.append(
            f"| {name} | {_ms(v['onnx']['median'])} / {_ms(v['onnx']['p90'])} | "
            f"{_ms(v['stage']['median'])} / {_ms(v['stage']['p90'])} |"
        )
    return out


def tls_table(d: dict[str, Any]) -> list[str]:
    med = d["transport"]["median"]
    rows = [
        ("CPU per paced message", "paced_cpu_us_per_msg", "µs"),
        ("latency median", "latency_median_us", "µs"),
        ("latency 99th percentile", "latency_p99_us", "µs"),
        ("CPU per message, burst", "burst_cpu_us_per_msg", "µs"),
        ("burst throughput", "burst_msgs_per_s", "msg/s"),
    ]
    out = ["| quantity | plain TCP | mutual TLS | TLS / plain |", "| --- | ---: | ---: | ---: |"]
    for label, key, unit in rows:
        p, t = med["plain"][key], med["tls"][key]
        digits = 0 if unit == "msg/s" else 1
        out.append(f"| {label} | {p:,.{digits}f} {unit} | {t:,.{digits}f} {unit} | {t / p:.2f} |")
    return out


BENCH_PAGES: dict[str, tuple[str, Callable[[dict[str, Any]], list[str]]]] = {
    "cdr_codecs": ("the live engine's CDR fast path against `rosbags`, per message", cdr_table),
    "scaling": ("time per particle-filter update over particles and team size", scaling_table),
    "filter_vs_pfilter": (
        "relloc's filter against the research configuration on `pfilter`",
        pfilter_table,
    ),
    "adaptive_particles": ("the adaptive particle count against the fixed count", adaptive_table),
    "ranging_inference": (
        "range-error prediction time per variant (untrained weights: the cost "
        "does not depend on them)",
        ranging_table,
    ),
    "tls_cost": ("mutual TLS and access control against plain TCP on loopback", tls_table),
}


def bench_section(name: str, argv: list[str], json_path: Path, status: str) -> list[str]:
    title, table = BENCH_PAGES[name]
    command = " ".join(["python", f"benchmarks/{name}.py", *argv, "--json", f"{name}.json"])
    out = [f"### `{name}.py`: {title}", "", "```bash", command, "```", ""]
    if not json_path.exists():
        return [*out, f"Not run: {status}", ""]
    return [*out, *table(json.loads(json_path.read_text())), ""]


# ---------------------------------------------------------------- the page


INTRO = """\
# Results

Generated by `make results` (`scripts/results_pages.py`): it reruns every command below and
reads each figure from the command's `--json` file; rerun it to refresh this page. Data paths
are relative to the repository root; a run whose data is absent is marked as not run.

APE is the error of each robot's position relative to the reference robot (shared heading
frame) against ground truth interpolated at the estimate's time, after the warm-up. NEES is the
median normalised estimation error squared of the published covariance (2 when consistent);
95 % coverage is the share of estimates whose 95 % ellipse holds the truth. Where the
formation's orientation is unobservable (a team without odometry, standing still) the APE is a
figure of the gauge: the shape APE, after one rotation/reflection fitted for the whole run to
the published shapes, is then the score (– where the orientation was observed). The particle filter
starts from a uniform prior over the arena and is never aligned to ground truth;
`multilateration` fits one rotation/reflection for the whole run, `multilateration_oracle`
aligns every step to ground truth (an oracle, for reference only).

More: [the measurements behind the design](../explanation/measurements.md) (diagnoses, sweeps and
the figures they gave), [TIERS recordings over seeds](tiers.md),
[MRCLAM with every reference](mrclam_references_generated.md),
[filter kinds side by side](filter_kinds_generated.md), [benchmarks](#benchmarks) below.
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data"))
    parser.add_argument("--json-dir", type=Path, default=Path("out/results"))
    parser.add_argument("--out", type=Path, default=Path("docs/results/index.md"))
    parser.add_argument(
        "--generated",
        type=Path,
        default=Path("docs/generated"),
        help="where the first-run tutorial's output and plot go",
    )
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument(
        "--quick",
        action="store_true",
        help="the demo's single scenario and tiny benchmarks (for the tests)",
    )
    parser.add_argument(
        "--from-json",
        action="store_true",
        help="rewrite the page from the JSON already in --json-dir, running nothing",
    )
    args = parser.parse_args()
    args.json_dir.mkdir(parents=True, exist_ok=True)
    (args.json_dir / "bench").mkdir(exist_ok=True)
    table = evaluation_runs(args.data, args.quick)
    bench = benchmarks(args.quick)
    status_path = args.json_dir / "status.json"  # why a run or benchmark did not run
    if args.from_json:
        earlier = json.loads(status_path.read_text()) if status_path.exists() else {}
        missing = "no JSON from an earlier run in --json-dir"
        status = {
            name: "ok"
            if (args.json_dir / f"{name}.json").exists()
            else earlier.get("runs", {}).get(name, missing)
            for name in table
        }
        bench_status = {
            name: "ok"
            if (args.json_dir / "bench" / f"{name}.json").exists()
            else earlier.get("bench", {}).get(name, missing)
            for name in bench
        }
        first = "not rerun (--from-json)"
    else:
        with ThreadPoolExecutor(args.jobs) as pool:
            tutorial = pool.submit(first_run, args.generated.resolve(), args.quick)
            status = dict(
                zip(
                    table,
                    pool.map(lambda kv: run_one(*kv, args.json_dir), table.items()),
                    strict=True,
                )
            )
            first = tutorial.result()
        # Benchmarks time things: one at a time, after the runs, on an otherwise idle machine.
        bench_status = {
            name: bench_one(name, argv, args.json_dir / "bench") for name, argv in bench.items()
        }
        status_path.write_text(json.dumps({"runs": status, "bench": bench_status}, indent=2))
    lines = [INTRO, f"Machine: {machine()}.", "", "## Evaluation runs", ""]
    for name, argv in table.items():
        lines += run_section(name, argv, args.json_dir / f"{name}.json", status[name])
    lines += [
        "## Benchmarks",
        "",
        "From `benchmarks/` (what each measures and its options: `benchmarks/README.md`),",
        "the ones that take seconds, run one after the other after the runs above. Times",
        "are this machine's and move with its load; the ratios measured in one process",
        "are the figures to compare.",
        "",
    ]
    for name, argv in bench.items():
        lines += bench_section(
            name, argv, args.json_dir / "bench" / f"{name}.json", bench_status[name]
        )
    args.out.write_text("\n".join(lines).rstrip() + "\n")
    ok = sum(s == "ok" for s in [*status.values(), *bench_status.values()])
    print(
        f"wrote {args.out}: {ok} of {len(status) + len(bench_status)} runs and benchmarks; "
        f"first-run tutorial: {first}"
    )


if __name__ == "__main__":
    main()
