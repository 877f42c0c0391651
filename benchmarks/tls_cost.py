"""The cost of mutual TLS and access control against plain TCP, as ratios in the same run.

Usage::

    python benchmarks/tls_cost.py [--messages 3000] [--rate 1000] [--rounds 3]
                                  [--rectangle-runs 0] [--reorder-window 0.1]
                                  [--readme FILE] [--json FILE]

Transport: two peer sessions on loopback, a publisher with the ``team`` role and a subscriber
with the ``serve`` role of a ``relloc secure init`` directory (mutual TLS, the team's access
control) against the same two over plain TCP, alternated in every round (plain, TLS, plain,
TLS, ...). Each phase opens the pair, waits for the link, sends 200 messages to warm up, then
``--messages`` odometry messages (``nav_msgs/Odometry`` CDR, 8-byte attachment with the send
time) paced at ``--rate`` per second and, after them, the same count as fast as it can
(congestion control ``BLOCK``: none is dropped). It
measures the process's CPU time per message (both ends, Python included) and the latency
of each paced message (send to callback, one clock), and prints the medians over the rounds
and the ratios TLS / plain.

Rectangle (``--rectangle-runs N``): N times, alternating, ``relloc sim-robots``, ``serve`` and
``navigate`` over plain TCP and over ``--secure`` (the small rectangle at twice real time, the
processes of ``tests/test_navigation_live.py``, serve with ``--reorder-window``, 0.1 s as
those tests use, so that a run repeats): the median tracking error (true position against the
path) and the APE median of the published estimates of r2 (against the true relative
position), per transport; ``--readme FILE`` writes their table between FILE's
``tls_rectangle`` markers.
"""

from __future__ import annotations

import argparse
import json
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from relloc.evaluation.pages import write_between
from relloc.events import OdometryEvent
from relloc.live import ZenohOptions, free_tcp_port, open_session, simulated_team
from relloc.live.secure.certificates import write_secure_dir
from relloc.ros.messages import encode, odometry_msg

REPO = Path(__file__).resolve().parents[1]
KEY = "r1/odom"


def _pair(mode: str, folder: Path) -> tuple[Any, Any]:
    """(publisher, subscriber) sessions, linked."""
    port = free_tcp_port()
    if mode == "plain":
        sub = open_session(ZenohOptions(listen=(f"tcp/127.0.0.1:{port}",), multicast=False))
        pub = open_session(ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), multicast=False))
    else:
        ep = f"tls/127.0.0.1:{port}"
        sub = open_session(
            ZenohOptions(config_file=folder / "serve.json5", listen=(ep,), multicast=False)
        )
        pub = open_session(
            ZenohOptions(config_file=folder / "team.json5", connect=(ep,), multicast=False)
        )
    end = time.monotonic() + 10
    while not pub.info.links() and time.monotonic() < end:
        time.sleep(0.01)
    return pub, sub


def _phase(mode: str, folder: Path, messages: int, rate: float) -> dict[str, float]:
    pub_session, sub_session = _pair(mode, folder)
    payload = encode(odometry_msg(OdometryEvent(1.7e9, "r1", 1.0, 2.0, 0.3, 0.2, 0.1)))
    latencies: list[float] = []
    count = [0]
    done = threading.Event()
    target = [0]

    def on_sample(sample: Any) -> None:
        sent = struct.unpack("<d", sample.attachment.to_bytes())[0]
        latencies.append(time.perf_counter() - sent)
        count[0] += 1
        if count[0] >= target[0]:
            done.set()

    sub = sub_session.declare_subscriber(KEY, on_sample)
    import zenoh

    pub = pub_session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
    end = time.monotonic() + 10
    while not pub.matching_status.matching and time.monotonic() < end:
        time.sleep(0.01)
    try:

        def send(n: int, period: float) -> float:
            """Send ``n`` messages (paced, or back to back when ``period`` is 0); the CPU
            seconds until the last one arrived."""
            done.clear()
            count[0] = 0
            target[0] = n
            latencies.clear()
            cpu = time.process_time()
            start = time.perf_counter()
            for i in range(n):
                if period:
                    delay = start + i * period - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                pub.put(payload, attachment=struct.pack("<d", time.perf_counter()))
            if not done.wait(30):
                raise RuntimeError(f"{mode}: {count[0]} of {n} messages arrived")
            return time.process_time() - cpu

        send(200, 1e-3)
        paced_cpu = send(messages, 1.0 / rate)
        lat = np.array(latencies) * 1e6
        t0 = time.perf_counter()
        burst_cpu = send(messages, 0.0)
        burst_wall = time.perf_counter() - t0
    finally:
        sub.undeclare()
        pub.undeclare()
        pub_session.close()
        sub_session.close()
    return {
        "paced_cpu_us_per_msg": 1e6 * paced_cpu / messages,
        "latency_median_us": float(np.median(lat)),
        "latency_p99_us": float(np.percentile(lat, 99)),
        "burst_cpu_us_per_msg": 1e6 * burst_cpu / messages,
        "burst_msgs_per_s": messages / burst_wall,
    }


def transport(folder: Path, messages: int, rate: float, rounds: int) -> dict[str, Any]:
    runs: dict[str, list[dict[str, float]]] = {"plain": [], "tls": []}
    for r in range(rounds):
        order = ("plain", "tls") if r % 2 == 0 else ("tls", "plain")
        for mode in order:
            runs[mode].append(_phase(mode, folder, messages, rate))
    medians = {
        mode: {k: statistics.median(run[k] for run in rs) for k in rs[0]}
        for mode, rs in runs.items()
    }
    ratios = {k: medians["tls"][k] / medians["plain"][k] for k in medians["plain"]}
    return {"runs": runs, "median": medians, "ratio_tls_over_plain": ratios}


# ============================================================================ rectangle
def _rectangle(secure: Path | None, tmp: Path, team: Path, window: float) -> dict[str, float]:
    """One live rectangle; tracking error and APE median of r2 (m)."""
    from relloc.live import EstimateCollector
    from relloc.navigation.path import load_path

    small = REPO / "configs" / "paths" / "small_rectangle.toml"
    p_sim, p_serve = free_tcp_port(), free_tcp_port()
    scheme = "tls" if secure else "tcp"
    flags = ["--no-multicast", *(["--secure", str(secure)] if secure else [])]

    def ep(port: int) -> str:
        return f"{scheme}/127.0.0.1:{port}"

    def start(*args: str, log: str) -> subprocess.Popen[bytes]:
        with (tmp / log).open("wb") as fh:
            return subprocess.Popen(
                [sys.executable, "-m", "relloc.cli", *args],
                stdout=fh,
                stderr=subprocess.STDOUT,
                cwd=REPO,
            )

    procs = [
        start("sim-robots", "--scenario", "nav", "--config", str(team), "--rate", "2", "--duration", "120",
              "--json", str(tmp / "sim.json"), *flags, "--listen", ep(p_sim), log="sim.log"),
        start("serve", "--config", str(team), "--clock-rate", "2", "--reorder-window", str(window),
              *flags, "--listen", ep(p_serve),
              "--connect", ep(p_sim), log="serve.log"),
    ]  # fmt: skip
    options = ZenohOptions(
        config_file=secure / "navigate.json5" if secure else None,
        connect=(ep(p_serve),),
        multicast=False,
    )
    watcher = open_session(options)
    from relloc.config import TeamConfig

    collector = EstimateCollector(watcher, TeamConfig.load(team))
    nav = start("navigate", "--config", str(team), "--robot", "r2", "--path", str(small), "--clock-rate", "2",
                "--duration", "50", "--json", str(tmp / "nav.json"), *flags, "--connect", ep(p_sim),
                "--connect", ep(p_serve), log="nav.log")  # fmt: skip
    try:
        code = nav.wait(timeout=90)
    finally:
        for p in (nav, *reversed(procs)):
            if p.poll() is None:
                p.send_signal(2)
                p.wait(timeout=20)
        estimates = collector.estimates()
        collector.close()
        watcher.close()
    if code != 0:
        raise RuntimeError(f"navigate ended with {code}: {(tmp / 'nav.log').read_text()}")
    summary = json.loads((tmp / "nav.json").read_text())
    truth = json.loads((tmp / "sim.json").read_text())["truth"]
    r2, r0 = np.array(truth["r2"]), np.array(truth["r0"])
    rel = r2[:, 1:3] - r0[:, 1:3]
    window = (r2[:, 0] >= summary["path_start_t"]) & (r2[:, 0] <= summary["end_t"])
    tracking = float(np.median(load_path(small).distance(rel[window])))
    t = np.array([e.t for e in estimates])
    est = np.array([e.positions["r2"] for e in estimates])
    keep = t >= r2[0, 0] + 10.0  # the demo's warm-up
    true = np.column_stack([np.interp(t[keep], r2[:, 0], rel[:, i]) for i in range(2)])
    ape = float(np.median(np.linalg.norm(est[keep] - true, axis=1)))
    return {
        "tracking_median_m": tracking,
        "ape_median_m": ape,
        "completed": bool(summary["completed"]),
    }


def rectangle(runs: int, window: float) -> dict[str, Any]:
    out: dict[str, list[dict[str, float]]] = {"plain": [], "tls": []}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        team = tmp / "team.toml"
        subprocess.run([sys.executable, "-m", "relloc.cli", "sim-robots", "--scenario", "nav", "--config-only",
                        "--write-config", str(team), "--particles", "4000"], check=True, cwd=REPO, capture_output=True)  # fmt: skip
        from relloc.config import TeamConfig

        write_secure_dir(TeamConfig.load(team), tmp / "sec")
        for r in range(runs):
            for mode in ("plain", "tls") if r % 2 == 0 else ("tls", "plain"):
                run_dir = tmp / f"{mode}{r}"
                run_dir.mkdir()
                out[mode].append(
                    _rectangle(tmp / "sec" if mode == "tls" else None, run_dir, team, window)
                )
    medians = {
        m: {
            k: statistics.median(run[k] for run in rs)
            for k in ("tracking_median_m", "ape_median_m")
        }
        for m, rs in out.items()
    }
    return {"runs": out, "median": medians}


def rectangle_table(rect: dict[str, Any], window: float) -> str:
    """The Markdown table of :func:`rectangle`'s runs (what ``--readme`` writes)."""
    runs = len(rect["runs"]["plain"])
    lines = [
        f"Written by `benchmarks/tls_cost.py --rectangle-runs {runs} --readme` (serve "
        f"`--reorder-window {window}`; runs alternated, {runs} per transport):",
        "",
        "| transport | tracking error, median (min-max) | APE of r2, median (min-max) |",
        "|---|---:|---:|",
    ]
    for mode, label in (("plain", "plain TCP"), ("tls", "mutual TLS")):
        cells = []
        for key in ("tracking_median_m", "ape_median_m"):
            values = [run[key] for run in rect["runs"][mode]]
            cells.append(f"{statistics.median(values):.3f} m ({min(values):.3f}-{max(values):.3f})")
        lines.append(f"| {label} | {cells[0]} | {cells[1]} |")
    diff = {
        k: rect["median"]["tls"][k] - rect["median"]["plain"][k]
        for k in ("tracking_median_m", "ape_median_m")
    }
    lines.append(
        f"| TLS - plain | {diff['tracking_median_m']:+.3f} m | {diff['ape_median_m']:+.3f} m |"
    )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--messages", type=int, default=3000)
    ap.add_argument("--rate", type=float, default=1000.0, help="paced messages per second")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--rectangle-runs", type=int, default=0, help="live rectangles per transport")
    ap.add_argument(
        "--reorder-window", type=float, default=0.1, help="serve's, in the rectangles (s)"
    )
    ap.add_argument(
        "--readme", type=Path, default=None, help="write the rectangles' table into FILE"
    )
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    _, config = simulated_team(seed=0, duration=1.0)
    result: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d) / "sec"
        write_secure_dir(config, folder)
        result["transport"] = tr = transport(folder, args.messages, args.rate, args.rounds)
    print(f"{'':24}{'plain TCP':>12}{'mutual TLS':>12}{'TLS/plain':>11}")
    for k, ratio in tr["ratio_tls_over_plain"].items():
        print(f"{k:24}{tr['median']['plain'][k]:12.1f}{tr['median']['tls'][k]:12.1f}{ratio:11.2f}")
    if args.rectangle_runs:
        result["rectangle"] = rect = rectangle(args.rectangle_runs, args.reorder_window)
        for mode, runs in rect["runs"].items():
            for run in runs:
                print(
                    f"rectangle {mode:6}: tracking {run['tracking_median_m']:.3f} m, APE {run['ape_median_m']:.3f} m"
                )
        for mode, m in rect["median"].items():
            print(
                f"rectangle {mode:6} median: tracking {m['tracking_median_m']:.3f} m, APE {m['ape_median_m']:.3f} m"
            )
        if args.readme:
            write_between(args.readme, "tls_rectangle", rectangle_table(rect, args.reorder_window))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
