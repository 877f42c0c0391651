"""CPU, peak memory and end-to-end latency of ``relloc serve``.

    .venv/bin/python benchmarks/serve_resources.py --json out/bench/resources.json

Runs the server as a subprocess (so that its CPU time and peak RSS can be read from ``/proc``),
feeds it over Zenoh on loopback (five simulated robots, the paper's team, and/or the TIERS
shortbag replayed), and measures the latency from a message's publication to the publication
of the estimate it triggered (the server's ``--trace`` key carries the trigger's send time).
The paper's Table II reports the same quantities; docs/explanation/live-engine.md sets ours beside them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from relloc.cli import argtypes
from relloc.cli.common import options_from_args
from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.live import (
    SIM_TIME_BASE,
    EstimateCollector,
    ReplayOptions,
    ZenohOptions,
    ape_against_bag,
    free_tcp_port,
    open_session,
    publish_events,
    replay_bag,
    simulated_team,
)
from relloc.live.resources import (
    CpuSampler,
    percentiles,
    proc_cpu_seconds,
    proc_memory_mb,
    round_finite,
    thread_cpu_seconds,
)

SHORTBAG = "multi4_shortbag_20221011"
"""The shared TIERS recording of the ``shortbag`` case."""
REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class BenchOptions:
    """Which cases to run and how."""

    particles: tuple[int | None, ...] = (None,)
    """Particle counts to serve with; ``None``: the shipped default settings (the config's
    ``[filter] particles`` and adaptive count, nothing overridden)."""
    settle: float = 10.0
    """Seconds of feeding after which the filter counts as converged: the CPU is also reported
    over the rest of the run (``cpu_percent_converged``)."""
    scenarios: tuple[str, ...] = ("sim5", "shortbag")
    sim_duration: float = 30.0
    rate: float = 1.0
    reorder_window: float = 0.0
    seed: int = 0
    bag: Path | None = None
    bag_config: Path | None = None
    json_path: Path | None = None


def _bench_case(
    scenario: str,
    particles: int | None,
    opts: BenchOptions,
    workdir: Path,
    say: Callable[[str], None],
) -> dict[str, Any]:
    """One serve subprocess fed over loopback; the server's figures while it was fed."""
    if scenario == "sim5":
        sim, config = simulated_team(opts.seed, opts.sim_duration)
        config_path = workdir / "sim5.toml"
        config.save(config_path)
        robots = len(config.robots)
    elif scenario == "shortbag":
        if opts.bag is None or opts.bag_config is None:
            raise FileNotFoundError("the shortbag case needs --bag and --bag-config")
        config_path = opts.bag_config
        config = TeamConfig.load(config_path)
        robots = len(config.robots)
    else:
        raise ValueError(f"unknown scenario {scenario!r}: choose sim5 or shortbag")
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    label = "default" if particles is None else str(particles)
    summary_path = workdir / f"serve_{scenario}_{label}.json"
    log_path = workdir / f"serve_{scenario}_{label}.log"
    cmd = [
        sys.executable, "-m", "relloc.cli", "serve",
        "--config", str(config_path),
        *([] if particles is None else ["--particles", str(particles)]),
        "--seed", str(opts.seed),
        "--listen", endpoint,
        "--no-multicast",
        "--trace",
        "--reorder-window", str(opts.reorder_window),
        "--clock-rate", str(opts.rate),
        "--json", str(summary_path),
        "--duration", "600",
    ]  # fmt: skip
    say(f"[{scenario}, {label} particles] serve: {' '.join(cmd[2:])}")
    with log_path.open("w") as log_fh:
        proc = subprocess.Popen(cmd, stdout=log_fh, stderr=subprocess.STDOUT)
    session = open_session(ZenohOptions(connect=(endpoint,), multicast=False))
    collector = EstimateCollector(session, config)
    served = config.filter.particles if particles is None else particles
    result: dict[str, Any] = {
        "scenario": scenario,
        "robots": robots,
        "particles": served,
        "settings": label,
        "adaptive": particles is None and config.filter.adaptive.particle_count != "fixed",
    }
    sampler: CpuSampler | None = None
    try:
        t_spawn = time.time()
        cpu: dict[str, float] = {}
        threads: dict[str, dict[str, float]] = {}

        def on_start() -> None:
            nonlocal sampler
            cpu["start"] = proc_cpu_seconds(proc.pid)
            cpu["wall_start"] = time.time()
            threads["start"] = thread_cpu_seconds(proc.pid)
            sampler = CpuSampler(proc.pid)

        def server_died() -> bool:
            return proc.poll() is not None

        base = SIM_TIME_BASE
        if scenario == "sim5":
            stats = publish_events(
                sim.events(), config, session, rate=opts.rate, time_base=base,
                wait=60.0, stop=server_died, on_start=on_start,
            )  # fmt: skip
        else:
            assert opts.bag is not None
            stats = replay_bag(
                opts.bag, config, session, ReplayOptions(rate=opts.rate, wait=60.0),
                stop=server_died, on_start=on_start,
            )  # fmt: skip
        if stats.unmatched or "start" not in cpu:
            raise RuntimeError(f"the server never subscribed ({stats.unmatched}); see {log_path}")
        time.sleep(0.5)  # the tail of the stream reaches the server
        if proc.poll() is not None:
            raise RuntimeError(f"serve exited early (status {proc.returncode}); see {log_path}")
        t_end = time.time()
        wall = t_end - cpu["wall_start"]
        cpu_s = proc_cpu_seconds(proc.pid) - cpu["start"]
        mem = proc_memory_mb(proc.pid)
        by_thread = thread_cpu_seconds(proc.pid)
        if sampler is not None:
            sampler.stop()
            converged = sampler.percent_between(cpu["wall_start"] + opts.settle, t_end)
        else:
            converged = math.nan
        result["cpu_percent_converged"] = round_finite(converged, 2)
        result["settle_s"] = opts.settle
        result["converged_window_s"] = round(max(wall - opts.settle, 0.0), 2)
        result["thread_cpu_s"] = {
            k: round(v - threads["start"].get(k, 0.0), 3)
            for k, v in sorted(by_thread.items(), key=lambda kv: -kv[1])
            if v - threads["start"].get(k, 0.0) > 0.0
        }
        result.update(
            {
                "startup_s": round(cpu["wall_start"] - t_spawn, 2),
                "startup_cpu_s": round(cpu["start"], 2),
                "fed_s": round(wall, 2),
                "messages": stats.messages,
                "message_rate_hz": round(stats.messages / max(wall, 1e-9), 1),
                "publisher_max_behind_ms": round(1e3 * stats.max_behind_s, 2),
                "cpu_percent": round(100.0 * cpu_s / wall, 2),
                "peak_rss_mb": round(mem.get("VmHWM", math.nan), 1),
                "rss_mb": round(mem.get("VmRSS", math.nan), 1),
                # of it: the process's own memory, and mapped files (shared libraries)
                "rss_anon_mb": round(mem.get("RssAnon", math.nan), 1),
                "rss_file_mb": round(mem.get("RssFile", math.nan), 1),
            }
        )
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        result["serve_exit"] = proc.returncode
        time.sleep(0.2)
        traces = [r for r in collector.traces() if r.get("trigger_sent") is not None]
        result["latency_publish"] = percentiles(
            [r["published"] - r["trigger_sent"] for r in traces]
        )
        result["latency_receive"] = percentiles([r["received"] - r["trigger_sent"] for r in traces])
        result["latency_compute"] = percentiles(
            [r["published"] - r["trigger_received"] for r in traces]
        )
        estimates = collector.estimates()
        result["estimates"] = len(estimates)
        if summary_path.exists():
            summary = json.loads(summary_path.read_text())
            pf = summary.get("methods", {}).get("pf", {})
            result["localizer_rejected"] = pf.get("rejected", {})
            result["source_rejected"] = summary.get("source", {}).get("rejected", {})
            result["engine_compute_s"] = pf.get("compute_s")
            result["engine_thread_cpu_s"] = summary.get("engine_thread_cpu_s")
            result["serve_uptime_s"] = summary.get("uptime_s")
            result["final_particles"] = summary.get("methods", {}).get("pf", {}).get("particles")
        if scenario == "shortbag" and opts.bag is not None:
            ape = ape_against_bag(estimates, opts.bag, config)
            result["ape_mean_median_m"] = round_finite(ape["mean_median"])
        else:
            result["ape_mean_median_m"] = round_finite(
                _sim_ape(sim, config, estimates, base, warmup=10.0)
            )
    finally:
        if sampler is not None:
            sampler.stop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        collector.close()
        session.close()
    return result


def _sim_ape(
    sim: Any, config: TeamConfig, estimates: list[Estimate], base: float, warmup: float
) -> float:
    """Mean over robots of the median APE of served estimates of a simulation (after warm-up);
    ``base`` is the time added to the simulator's stamps when they were published."""
    import numpy as np

    medians = []
    for robot in config.others:
        errs = []
        for est in estimates:
            t = est.t - base
            if t < warmup or robot not in est.positions or t > sim.duration:
                continue
            p = sim.true_pose(robot, t)
            q = sim.true_pose(config.reference, t)
            ex, ey = est.positions[robot]
            errs.append(math.hypot(ex - (p[0] - q[0]), ey - (p[1] - q[1])))
        if errs:
            medians.append(float(np.median(errs)))
    return statistics.fmean(medians) if medians else math.nan


def bench_resources(opts: BenchOptions, say: Callable[[str], None] = print) -> dict[str, Any]:
    """Run every (scenario, particles) case; returns ``{"cases": [...], ...}`` (and writes JSON)."""
    cases = []
    with tempfile.TemporaryDirectory(prefix="relloc-bench-") as tmp:
        for scenario in opts.scenarios:
            for n in opts.particles:
                case = _bench_case(scenario, n, opts, Path(tmp), say)
                say(_case_line(case))
                cases.append(case)
    result = {
        "host": {"cpus": os.cpu_count(), "python": sys.version.split()[0]},
        "rate": opts.rate,
        "reorder_window_s": opts.reorder_window,
        "seed": opts.seed,
        "cases": cases,
    }
    if opts.json_path is not None:
        opts.json_path.parent.mkdir(parents=True, exist_ok=True)
        opts.json_path.write_text(json.dumps(result, indent=2))
    return result


def _case_line(c: dict[str, Any]) -> str:
    lat = c["latency_publish"]
    return (
        f"{c['scenario']:>8} {c['robots']} robots {c['particles']:>6} particles"
        f"{' (adaptive, last ' + str(c.get('final_particles')) + ')' if c.get('adaptive') else ''}: "
        f"CPU {c['cpu_percent']:.1f} % of a core ({c['cpu_percent_converged']} % after "
        f"{c['settle_s']:g} s), peak RSS {c['peak_rss_mb']:.0f} MB "
        f"(at the end {c['rss_anon_mb']:.0f} own + {c['rss_file_mb']:.0f} mapped files), "
        f"latency p50 {lat['p50_ms']} ms p95 {lat['p95_ms']} ms (n={lat['n']}), "
        f"{c['message_rate_hz']} msg/s, APE {c['ape_mean_median_m']} m"
    )


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    bag = Path(args.bag) if args.bag else REPO.parent / "shared" / "data" / "tiers" / SHORTBAG
    bag_config = (
        Path(args.bag_config)
        if args.bag_config
        else REPO / "configs" / "tiers" / f"{SHORTBAG}.toml"
    )
    scenarios = tuple(s.strip() for s in args.scenarios.split(",") if s.strip())
    if "shortbag" in scenarios and not bag.exists():
        if args.bag:
            print(f"bag not found: {bag}", file=sys.stderr)
            return 2
        print(f"skipping the shortbag case: {bag} not found")
        scenarios = tuple(s for s in scenarios if s != "shortbag")
    try:
        particles = tuple(
            None if p.strip() == "default" else argtypes.count(p.strip())
            for p in args.particles.split(",")
        )
    except (ValueError, argparse.ArgumentTypeError):
        print(
            f"--particles must be 'default' or counts like default,400,4000, got {args.particles!r}",
            file=sys.stderr,
        )
        return 2
    opts = options_from_args(
        BenchOptions, args, particles=particles, scenarios=scenarios, bag=bag, bag_config=bag_config
    )
    bench_resources(opts)
    if opts.json_path:
        print(f"figures written to {opts.json_path}")
    return 0


def _parser() -> argparse.ArgumentParser:
    res = argparse.ArgumentParser(
        description="Start relloc serve and a publisher on loopback for each scenario and "
        "particle count; measure CPU, peak RSS and estimate latency (docs/explanation/live-engine.md).",
    )
    res.add_argument(
        "--particles",
        default="default",
        help="comma-separated particle counts; 'default': the shipped settings (the config's count, adaptive)",
    )
    res.add_argument(
        "--settle",
        type=argtypes.non_negative,
        default=10.0,
        metavar="S",
        help="seconds of feeding before the filter counts as converged (CPU also reported after it)",
    )
    res.add_argument(
        "--scenarios",
        default="sim5,shortbag",
        help="sim5 (5 simulated robots), shortbag (4 robots, TIERS)",
    )
    res.add_argument(
        "--duration",
        dest="sim_duration",
        type=argtypes.positive,
        default=30.0,
        help="length of the simulated run (s)",
    )
    res.add_argument("--rate", type=argtypes.positive, default=1.0, help="publishing speed factor")
    res.add_argument(
        "--reorder-window",
        type=argtypes.non_negative,
        default=0.0,
        metavar="S",
        help="the server's --reorder-window",
    )
    res.add_argument("--seed", type=argtypes.seed, default=0, help="random seed")
    res.add_argument(
        "--bag", type=Path, default=None, help=f"default ../shared/data/tiers/{SHORTBAG}"
    )
    res.add_argument(
        "--bag-config", type=Path, default=None, help=f"default configs/tiers/{SHORTBAG}.toml"
    )
    res.add_argument(
        "--json",
        dest="json_path",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the figures as JSON",
    )
    return res


if __name__ == "__main__":
    sys.exit(main())
