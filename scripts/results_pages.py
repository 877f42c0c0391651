"""Rerun the evaluation commands and write the generated results page from their JSON.

    .venv/bin/python scripts/results_pages.py --out docs/results_generated.md   # make results

The runs are those of ``scripts/figures_check.py`` (the demo, the self-calibration demo, the
TIERS shortbag seeds 0-4, ``pair_range`` with calibrated and online biases, MRCLAM Dataset 6;
a run whose data is absent is listed as skipped). The page names each run's command and the
machine it ran on, and every figure in it is read from the run's ``--json`` file: nothing is
copied by hand.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from figures_check import runs  # a sibling script, not a package


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
        names = [ln.split(":", 1)[1].strip() for ln in cpuinfo.read_text().splitlines()
                 if ln.startswith("model name")]
        model = names[0] if names else ""
    return (f"{model or cpu}, {os.cpu_count()} CPUs, {platform.system()} {platform.release()}, "
            f"Python {platform.python_version()}, NumPy {numpy.__version__}")


def scenario_table(name: str, scenario: dict[str, Any]) -> list[str]:
    nav = scenario.get("navigation")
    if "methods" not in scenario:
        return [f"**{name}**: positioning APE median {_fmt((nav or {}).get('ape_median'))} m, "
                f"tracking error median {_fmt((nav or {}).get('tracking_median'))} m.", ""]
    out = [f"**{name}**: reference `{scenario.get('reference')}`, warm-up "
           f"{_fmt(scenario.get('warmup_s'), 0)} s, {_fmt(scenario.get('duration_s'), 1)} s long.", "",
           "| method | robot | APE median (m) | APE RMSE (m) | NEES median | 95 % coverage |",
           "| --- | --- | --- | --- | --- | --- |"]
    for method, m in scenario.get("methods", {}).items():
        for robot, r in m.get("robots", {}).items():
            out.append(f"| {method} | {robot} | {_fmt(r.get('ape_median'))} | "
                       f"{_fmt(r.get('ape_rmse'))} | {_fmt(r.get('nees_median'), 2)} | "
                       f"{_fmt(r.get('coverage95'), 2)} |")
    if nav:
        out += ["", f"Navigation: positioning APE median {_fmt(nav.get('ape_median'))} m, tracking "
                f"error median {_fmt(nav.get('tracking_median'))} m."]
    return [*out, ""]


def run_section(name: str, argv: list[str], json_path: Path, status: str) -> list[str]:
    command = " ".join(["relloc", *argv, "--json", f"{name}.json"])
    out = [f"## {name}", "", "```bash", command, "```", ""]
    if not json_path.exists():
        return [*out, f"Not run: {status}", ""]
    data = json.loads(json_path.read_text())
    for scenario_name, scenario in data.get("scenarios", {}).items():
        out += scenario_table(scenario_name, scenario)
    return out


def run_one(name: str, argv: list[str], folder: Path) -> str:
    (folder / f"{name}.json").unlink(missing_ok=True)  # no stale figures from an earlier run
    cmd = [sys.executable, "-m", "relloc.cli", *argv, "--no-progress",
           "--out", str(folder / name), "--json", str(folder / f"{name}.json")]
    done = subprocess.run(cmd, capture_output=True, text=True)
    return "ok" if done.returncode == 0 else done.stderr.strip().splitlines()[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data"))
    parser.add_argument("--json-dir", type=Path, default=Path("out/results"))
    parser.add_argument("--out", type=Path, default=Path("docs/results_generated.md"))
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    args.json_dir.mkdir(parents=True, exist_ok=True)
    table = runs(args.data)
    with ThreadPoolExecutor(args.jobs) as pool:
        status = dict(zip(table, pool.map(lambda kv: run_one(*kv, args.json_dir), table.items()),
                          strict=True))
    lines = ["# Generated results", "",
             "Written by `make results` (`scripts/results_pages.py`) from the `--json` of each",
             "command below; rerun it to refresh this page. Data paths are relative to the",
             "repository root.", "", f"Machine: {machine()}.", ""]
    for name, argv in table.items():
        lines += run_section(name, argv, args.json_dir / f"{name}.json", status[name])
    args.out.write_text("\n".join(lines).rstrip() + "\n")
    print(f"wrote {args.out}: {sum(s == 'ok' for s in status.values())} of {len(status)} runs")


if __name__ == "__main__":
    main()
