"""``relloc serve`` against a bare Zenoh subscriber on the same stream, side by side.

    .venv/bin/python benchmarks/serve_vs_subscriber.py [--hog] [--readme benchmarks/README.md]

The benchmark's own session listens on a loopback port and publishes (five simulated robots,
``sim5``, and/or the TIERS shortbag replayed, ``shortbag``); two subprocesses connect to it and
receive the same messages: ``relloc serve`` at the shipped defaults and a subscriber to the
same key expressions whose callback does nothing (it imports only ``zenoh``). Both processes'
CPU is sampled from ``/proc``; the ratio after convergence (``--settle`` s of feeding) is what
relloc costs beyond receiving the messages at all. Also: the latency from publication to the
estimate (the server's trace), serve's peak RSS, the events passed on out of order and the
messages the filter dropped as late. ``--hog`` runs one busy-looping process beside them (a
loaded machine). serve takes its default NumPy filter step; ``RELLOC_COMPILED=1`` in the
environment measures the compiled one (it imports numba: about 130 MB more resident).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/: the shared modules
import bare_subscriber

from relloc.config import TeamConfig
from relloc.evaluation.pages import write_between
from relloc.live import (
    SIM_TIME_BASE,
    EstimateCollector,
    ReplayOptions,
    ZenohOptions,
    free_tcp_port,
    open_session,
    publish_events,
    replay_bag,
    simulated_team,
)
from relloc.live.resources import CpuSampler, percentiles, proc_memory_mb, round_finite
from relloc.sources.zenoh_source import ZenohSource

SHORTBAG = "multi4_shortbag_20221011"
"""The shared TIERS recording of the ``shortbag`` case."""
REPO = Path(__file__).resolve().parents[1]
LATE_REASONS = ("late_measurement", "out_of_order_odometry", "late")
"""Rejections that mean a message came too late for the filter (localizer and source)."""


@dataclass(frozen=True)
class Options:
    """Which cases to run and how."""

    scenarios: tuple[str, ...] = ("sim5", "shortbag")
    settle: float = 10.0
    sim_duration: float = 30.0
    hog: bool = False
    reorder_window: float | None = None
    """The server's ``--reorder-window``; ``None``: the shipped default."""
    seed: int = 0
    bag: Path = REPO.parent / "shared" / "data" / "tiers" / SHORTBAG
    bag_config: Path = REPO / "configs" / "tiers" / f"{SHORTBAG}.toml"


def _wait_for(pred: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.time() + timeout
    while not pred():
        if time.time() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _stop(proc: subprocess.Popen[Any]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run_case(
    scenario: str, opts: Options, workdir: Path, say: Callable[[str], None]
) -> dict[str, Any]:
    """One scenario: serve and the bare subscriber fed the same messages."""
    if scenario == "sim5":
        sim, config = simulated_team(opts.seed, opts.sim_duration)
        config_path = workdir / "sim5.toml"
        config.save(config_path)
    elif scenario == "shortbag":
        config_path = opts.bag_config
        config = TeamConfig.load(config_path)
    else:
        raise ValueError(f"unknown scenario {scenario!r}: choose sim5 or shortbag")
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    session = open_session(ZenohOptions(listen=(endpoint,), multicast=False))
    collector = EstimateCollector(session, config)
    summary_path = workdir / f"serve_{scenario}.json"
    log_path = workdir / f"serve_{scenario}.log"
    window = [] if opts.reorder_window is None else ["--reorder-window", str(opts.reorder_window)]
    serve_cmd = [
        sys.executable, "-m", "relloc.cli", "serve", "--config", str(config_path),
        "--seed", str(opts.seed), "--connect", endpoint, "--no-multicast", "--trace",
        *window, "--json", str(summary_path), "--duration", "600",
    ]  # fmt: skip
    exprs = ZenohSource(config).expressions
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if opts.hog else None
    with log_path.open("w") as log_fh:
        serve = subprocess.Popen(serve_cmd, stdout=log_fh, stderr=subprocess.STDOUT)
    bare = bare_subscriber.start([endpoint], exprs)
    samplers: dict[str, CpuSampler] = {}
    result: dict[str, Any] = {"scenario": scenario, "robots": len(config.robots), "hog": opts.hog}
    try:
        assert bare.stdout is not None
        if bare.stdout.readline().strip() != "ready":
            raise RuntimeError("the bare subscriber did not start")
        _wait_for(
            lambda: "relloc serve:" in log_path.read_text() or serve.poll() is not None,
            120,
            "serve",
        )
        if serve.poll() is not None:
            raise RuntimeError(f"serve exited early; see {log_path}")

        def on_start() -> None:
            samplers["serve"] = CpuSampler(serve.pid)
            samplers["bare"] = CpuSampler(bare.pid)
            result["t_start"] = time.time()

        def serve_died() -> bool:
            return serve.poll() is not None

        if scenario == "sim5":
            stats = publish_events(
                sim.events(), config, session, time_base=SIM_TIME_BASE, wait=60.0,
                stop=serve_died, on_start=on_start,
            )  # fmt: skip
        else:
            stats = replay_bag(
                opts.bag,
                config,
                session,
                ReplayOptions(wait=60.0),
                stop=serve_died,
                on_start=on_start,
            )
        time.sleep(0.5)  # the tail of the stream reaches both
        t_end = time.time()
        for s in samplers.values():
            s.stop()
        t0 = result.pop("t_start") + opts.settle
        cpu = {name: s.percent_between(t0, t_end) for name, s in samplers.items()}
        result["messages"] = stats.messages
        result["serve_cpu_percent"] = round_finite(cpu["serve"], 2)
        result["bare_cpu_percent"] = round_finite(cpu["bare"], 2)
        result["cpu_ratio"] = (
            round_finite(cpu["serve"] / cpu["bare"], 2) if cpu["bare"] > 0 else None
        )
        mem = proc_memory_mb(serve.pid)
        result["serve_peak_rss_mb"] = round(mem.get("VmHWM", math.nan), 1)
        # the RSS now, split: the process's own memory, and mapped files (shared libraries)
        result["serve_rss_anon_mb"] = round(mem.get("RssAnon", math.nan), 1)
        result["serve_rss_file_mb"] = round(mem.get("RssFile", math.nan), 1)
        result["bare_peak_rss_mb"] = round(proc_memory_mb(bare.pid).get("VmHWM", math.nan), 1)
        _stop(serve)
        _stop(bare)
        out, _ = bare.communicate(timeout=10)
        result["bare_received"] = bare_subscriber.received(out)
        time.sleep(0.2)
        traces = [r for r in collector.traces() if r.get("trigger_sent") is not None]
        result["latency"] = percentiles(
            [r["published"] - r["trigger_sent"] for r in traces if r["trigger_sent"] >= t0]
        )
        result["latency_all"] = percentiles([r["published"] - r["trigger_sent"] for r in traces])
        summary = json.loads(summary_path.read_text())
        rejected = dict(summary["source"]["rejected"])
        for m in summary["methods"].values():
            for k, v in m["rejected"].items():
                rejected[k] = rejected.get(k, 0) + v
        result["serve_received"] = summary["source"]["messages"]
        result["out_of_order"] = summary["source"]["out_of_order"]
        result["late_drops"] = sum(rejected.get(k, 0) for k in LATE_REASONS)
        result["late_drop_percent"] = round(
            100.0 * result["late_drops"] / max(stats.messages, 1), 3
        )
        result["rejected"] = rejected
        result["estimates"] = (
            summary["methods"]["pf"]["estimates"] if "pf" in summary["methods"] else None
        )
    finally:
        for s in samplers.values():
            s.stop()
        for p in (serve, bare, hog):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
        collector.close()
        session.close()
    say(_line(result))
    return result


def _line(c: dict[str, Any]) -> str:
    lat = c["latency"]
    return (
        f"{c['scenario']:>8}{' +hog' if c['hog'] else ''}: serve {c['serve_cpu_percent']} % vs bare "
        f"{c['bare_cpu_percent']} % of a core after convergence = {c['cpu_ratio']}x; latency after "
        f"it p95 {lat['p95_ms']} ms (p50 {lat['p50_ms']}, n={lat['n']}; whole run p95 "
        f"{c['latency_all']['p95_ms']} ms); peak RSS {c['serve_peak_rss_mb']} MB "
        f"(at the end {c['serve_rss_anon_mb']} own + {c['serve_rss_file_mb']} mapped files); "
        f"{c['messages']} msgs, {c['out_of_order']} out of order, {c['late_drops']} late drops "
        f"({c['late_drop_percent']} %)"
    )


def figures_table(cases: list[dict[str, Any]], context: str) -> str:
    """The Markdown figures of one run (what ``--readme`` writes)."""
    lines = [
        f"Written by `benchmarks/serve_vs_subscriber.py --readme` ({context}):",
        "",
        "| case | CPU serve / bare (after convergence) | ratio | latency p50 / p95 (after it) | "
        "latency p95 (whole run) | peak RSS | RSS own + files (end) | messages | out of order | late drops |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for c in cases:
        lat = c["latency"]
        lines.append(
            f"| {c['scenario']}{' + 1 CPU hog' if c['hog'] else ''} | {c['serve_cpu_percent']} % / "
            f"{c['bare_cpu_percent']} % | {c['cpu_ratio']}x | {lat['p50_ms']} / {lat['p95_ms']} ms | "
            f"{c['latency_all']['p95_ms']} ms | {c['serve_peak_rss_mb']:.0f} MB | "
            f"{c['serve_rss_anon_mb']:.0f} + {c['serve_rss_file_mb']:.0f} MB | {c['messages']} | {c['out_of_order']} | "
            f"{c['late_drops']} ({c['late_drop_percent']} %) |"
        )
    return "\n".join(lines)


def write_readme(path: Path, cases: list[dict[str, Any]], context: str) -> None:
    """Replace the text between the markers of ``path`` with this run's figures."""
    write_between(path, "serve_vs_subscriber", figures_table(cases, context))


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    scenarios = tuple(s.strip() for s in args.scenarios.split(",") if s.strip())
    opts = Options(
        scenarios=scenarios, settle=args.settle, sim_duration=args.duration, seed=args.seed,
        reorder_window=args.reorder_window,
        **({"bag": args.bag} if args.bag else {}),
        **({"bag_config": args.bag_config} if args.bag_config else {}),
    )  # fmt: skip
    if "shortbag" in scenarios and not opts.bag.exists():
        print(f"skipping the shortbag case: {opts.bag} not found")
        opts = Options(
            **{**opts.__dict__, "scenarios": tuple(s for s in scenarios if s != "shortbag")}
        )
    cases: list[dict[str, Any]] = []
    hogs = (False, True) if args.hog else (False,)
    with tempfile.TemporaryDirectory(prefix="relloc-bench-") as tmp:
        for hog in hogs:
            for scenario in opts.scenarios:
                case_opts = Options(**{**opts.__dict__, "hog": hog})
                cases.append(run_case(scenario, case_opts, Path(tmp), print))
    if args.json_path is not None:
        args.json_path.parent.mkdir(parents=True, exist_ok=True)
        args.json_path.write_text(json.dumps({"cases": cases}, indent=2))
    if args.readme is not None:
        from importlib.metadata import version

        window = "shipped default" if opts.reorder_window is None else f"{opts.reorder_window:g} s"
        step = "compiled" if os.environ.get("RELLOC_COMPILED") == "1" else "NumPy"
        context = (
            f"{step} filter step, reorder window {window}, settle {opts.settle:g} s, "
            f"seed {opts.seed}; "
            f"eclipse-zenoh {version('eclipse-zenoh')}, Python {sys.version.split()[0]}, "
            f"{os.cpu_count()} CPUs"
        )
        write_readme(args.readme, cases, context)
        print(f"wrote the figures into {args.readme}")
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description="relloc serve against a bare Zenoh subscriber, side by side."
    )
    p.add_argument("--scenarios", default="sim5,shortbag", help="sim5, shortbag (comma-separated)")
    p.add_argument(
        "--settle", type=float, default=10.0, help="seconds of feeding before convergence"
    )
    p.add_argument("--duration", type=float, default=30.0, help="length of the simulated run (s)")
    p.add_argument("--hog", action="store_true", help="also run every case with one CPU hog beside")
    p.add_argument(
        "--reorder-window", type=float, default=None, metavar="S", help="default: serve's own"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--bag", type=Path, default=None, help=f"default ../shared/data/tiers/{SHORTBAG}"
    )
    p.add_argument(
        "--bag-config", type=Path, default=None, help=f"default configs/tiers/{SHORTBAG}.toml"
    )
    p.add_argument("--json", dest="json_path", type=Path, default=None, metavar="FILE")
    p.add_argument(
        "--readme",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the figures between its markers",
    )
    return p


if __name__ == "__main__":
    sys.exit(main())
