"""A/B of the closed navigation loop over mutual TLS against plain TCP, runs alternated.

    .venv/bin/python scripts/transport_ab.py --runs 10 --out out/transport_ab \\
        --json out/transport_ab/transport_ab.json [--ape] [--markdown docs/navigation.md]

Each run is the setup of ``tests/test_secure.py``'s whole-system test without the attacker:
``relloc sim-robots --scenario nav --rate 2``, ``relloc serve --clock-rate 2 --reorder-window
0.1`` and ``relloc navigate --robot r2`` along ``configs/paths/small_rectangle.toml`` (``--clock-rate
2 --duration 50``) as processes on 127.0.0.1, a full mesh (serve and sim-robots listen, navigate
connects to both and listens), multicast off; the team config of ``sim-robots --config-only``
(4 000 particles). TLS: ``--secure DIR`` of ``relloc secure init`` and ``tls/`` endpoints;
plain: the same endpoints as ``tcp/``. Runs alternate (TLS, plain, TLS, ...), so that a slow
drift of the machine falls on both; every wait is on a process's exit, with a timeout.

Figures per run: r2's tracking error median (``check_small_rectangle`` and docs/navigation.md,
"Run-to-run spread"): the simulator's true r2 - r0 against the planned path, from reaching the
first waypoint (navigate's ``path_start_t``) to completing the path (``end_t``). The APE median
of the relative estimate: neither serve's nor navigate's ``--json`` carries the estimates, so
with ``--ape`` serve also writes ``--record rec.mcap`` (every pose it published) and the APE is
r2's recorded poses against the simulator's truth (r2 - r0, in the pose's frame) over the same
window; without ``--ape`` the setup is the test's exactly and the APE is left out (null).
A run that fails (navigate's exit code not 0, no summary) is kept with its error and left out
of the medians. ``--markdown FILE`` writes the table between the markers below (replacing what
is there; appended where the file has none).
"""

from __future__ import annotations

import argparse
import json
import shlex
import signal
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from relloc.estimate import BODY_FRAME, HEADING_FRAME, Estimate
from relloc.evaluation.metrics import GroundTruth, truth_in_frame
from relloc.events import GroundTruthEvent
from relloc.live import free_tcp_port
from relloc.navigation.path import load_path
from relloc.ros.messages import POSE_WITH_COVARIANCE_STAMPED, decode, stamp_to_sec

ROOT = Path(__file__).resolve().parent.parent
PATH = ROOT / "configs" / "paths" / "small_rectangle.toml"
ROBOT, PARTICLES = "r2", 4000
TRANSPORTS = ("tls", "plain")
NAV_TIMEOUT = 75.0
"""Seconds navigate may take (its --duration is 50 data seconds, 25 wall seconds at x2, after
sim-robots' wait for serve)."""
BEGIN, END = "<!-- transport_ab: begin -->", "<!-- transport_ab: end -->"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=10, help="runs per transport (default: 10)")
    p.add_argument(
        "--seed", type=int, default=0, help="sim-robots' and serve's --seed (default: 0)"
    )
    p.add_argument("--out", type=Path, default=ROOT / "out" / "transport_ab", help="run folders")
    p.add_argument("--json", type=Path, help="write every run and the medians")
    p.add_argument("--markdown", type=Path, help="write the table between the markers of FILE")
    p.add_argument("--ape", action="store_true", help="serve --record, and the APE of r2's poses")
    args = p.parse_args(argv)
    if args.runs < 1:
        p.error("--runs must be at least 1")
    return args


# ============================================================================ processes
def relloc(*args: str, log: Path) -> subprocess.Popen[bytes]:
    """Start ``relloc ARGS`` (this interpreter) with its output in ``log``."""
    with log.open("wb") as fh:
        return subprocess.Popen(
            [sys.executable, "-m", "relloc.cli", *args],
            stdout=fh,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
        )


def relloc_run(*args: str) -> None:
    """Run ``relloc ARGS`` to completion; raise with its output if it fails."""
    done = subprocess.run(
        [sys.executable, "-m", "relloc.cli", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    if done.returncode != 0:
        raise RuntimeError(f"relloc {shlex.join(args)} failed:\n{done.stdout}{done.stderr}")


def stop(proc: subprocess.Popen[bytes], timeout: float = 15.0) -> int:
    """SIGINT (each command then writes its --json), wait; kill if it hangs."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


def prepare(out: Path) -> tuple[Path, Path]:
    """The nav team's config (``sim-robots --config-only``) and its secure directory."""
    out.mkdir(parents=True, exist_ok=True)
    team = out / "team.toml"
    relloc_run("sim-robots", "--scenario", "nav", "--config-only", "--write-config", str(team),
               "--particles", str(PARTICLES))  # fmt: skip
    secure = out / "sec"
    relloc_run("secure", "init", "--config", str(team), "--out", str(secure), "--force")
    return team, secure


def drive(
    transport: str, run_dir: Path, team: Path, secure: Path, seed: int, ape: bool
) -> int | None:
    """One run of the three processes; navigate's exit code (None: it timed out)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    for stale in ("sim.json", "serve.json", "nav.json", "rec.mcap"):  # of an earlier invocation
        (run_dir / stale).unlink(missing_ok=True)
    scheme = "tls" if transport == "tls" else "tcp"

    def ep(port: int) -> str:
        return f"{scheme}/127.0.0.1:{port}"

    common = ["--no-multicast", *(["--secure", str(secure)] if transport == "tls" else [])]
    record = ["--record", str(run_dir / "rec.mcap")] if ape else []
    p_sim, p_serve, p_nav = free_tcp_port(), free_tcp_port(), free_tcp_port()
    procs: list[subprocess.Popen[bytes]] = []
    try:
        procs.append(relloc("sim-robots", "--scenario", "nav", "--config", str(team), "--seed", str(seed),
                            "--rate", "2", "--duration", "120", "--json", str(run_dir / "sim.json"),
                            *common, "--listen", ep(p_sim), log=run_dir / "sim.log"))  # fmt: skip
        procs.append(relloc("serve", "--config", str(team), "--seed", str(seed), "--clock-rate", "2",
                            "--reorder-window", "0.1", "--json", str(run_dir / "serve.json"), *record,
                            *common, "--listen", ep(p_serve), "--connect", ep(p_sim),
                            log=run_dir / "serve.log"))  # fmt: skip
        nav = relloc("navigate", "--config", str(team), "--robot", ROBOT, "--path", str(PATH),
                     "--clock-rate", "2", "--duration", "50", "--json", str(run_dir / "nav.json"),
                     *common, "--connect", ep(p_sim), "--connect", ep(p_serve), "--listen", ep(p_nav),
                     log=run_dir / "nav.log")  # fmt: skip
        procs.append(nav)
        try:
            return nav.wait(timeout=NAV_TIMEOUT)
        except subprocess.TimeoutExpired:
            return None
    finally:
        for proc in reversed(procs):
            stop(proc)


# ============================================================================ figures
def tracking_errors(summary: dict[str, Any], truth: dict[str, Any]) -> np.ndarray:
    """The true r2 - r0 against the path, from reaching the first waypoint to the end."""
    r2 = np.array(truth["truth"][ROBOT])
    r0 = np.array(truth["truth"][truth["reference"]])
    rel = r2[:, 1:3] - r0[:, 1:3]
    window = (r2[:, 0] >= summary["path_start_t"]) & (r2[:, 0] <= summary["end_t"])
    return load_path(PATH).distance(rel[window])


def recorded_poses(mcap: Path) -> list[Estimate]:
    """r2's poses serve published (``serve --record``), as one-robot estimates."""
    from rosbags.rosbag2 import Reader

    out = []
    with Reader(mcap) as reader:
        conns = [c for c in reader.connections if c.topic == f"/relloc/pf/{ROBOT}/pose"]
        for _, _, raw in reader.messages(conns):
            msg = decode(raw, POSE_WITH_COVARIANCE_STAMPED)
            frame_id = msg.header.frame_id
            pos = msg.pose.pose.position
            out.append(
                Estimate(
                    t=stamp_to_sec(msg.header.stamp),
                    method="pf",
                    reference=frame_id.removesuffix("/base_link"),
                    positions={ROBOT: (float(pos.x), float(pos.y))},
                    frame=BODY_FRAME if frame_id.endswith("/base_link") else HEADING_FRAME,
                )
            )
    return out


def ape_errors(
    estimates: list[Estimate], summary: dict[str, Any], truth: dict[str, Any]
) -> np.ndarray:
    """Distance of each estimate of r2 in the tracking window to the truth in its frame."""
    gt = GroundTruth(truth["reference"])
    for robot, poses in truth["truth"].items():
        for t, x, y, yaw in poses:
            gt.add(GroundTruthEvent(t, robot, x, y, yaw))
    errors = []
    for est in estimates:
        if not summary["path_start_t"] <= est.t <= summary["end_t"]:
            continue
        true = truth_in_frame(est, gt, ROBOT)
        if true is not None:
            x, y = est.positions[ROBOT]
            errors.append(float(np.hypot(x - true[0], y - true[1])))
    return np.array(errors)


def figures(run_dir: Path, code: int | None, ape: bool) -> dict[str, Any]:
    """A run's figures from its JSON files (``error`` set where the run failed)."""
    out: dict[str, Any] = {"nav_exit": code, "tracking_median": None, "ape_median": None}
    try:
        summary = json.loads((run_dir / "nav.json").read_text())
        truth = json.loads((run_dir / "sim.json").read_text())
    except (OSError, ValueError) as exc:
        out["error"] = f"no summary: {exc}"
        return out
    out.update(completed=summary["completed"], ended=summary["ended"])
    released = [s["t"] for s in summary["stops"] if s["reason"] == "released"]
    out["released_s"] = released[0] - truth["time_base"] if released else None
    if code != 0 or not summary["completed"] or summary["end_t"] is None:
        out["error"] = f"navigate exit {code}, ended {summary['ended']!r}"
        return out
    errors = tracking_errors(summary, truth)
    out.update(
        tracking_median=float(np.median(errors)),
        tracking_std=float(errors.std()),
        tracking_n=int(errors.size),
    )
    if ape:
        try:
            e = ape_errors(recorded_poses(run_dir / "rec.mcap"), summary, truth)
        except Exception as exc:  # a missing or truncated record: say so, keep the tracking
            out["error"] = f"no APE: {exc}"
        else:
            out.update(ape_median=float(np.median(e)) if e.size else None, ape_n=int(e.size))
    return out


def spread(values: list[float]) -> dict[str, Any]:
    """Median, min, max and count of the values (None where there are none)."""
    if not values:
        return {"median": None, "min": None, "max": None, "n": 0}
    return {
        "median": statistics.median(values),
        "min": min(values),
        "max": max(values),
        "n": len(values),
    }


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per transport and figure the spread; the TLS-minus-plain difference of the medians."""
    out: dict[str, Any] = {}
    for transport in TRANSPORTS:
        mine = [r for r in runs if r["transport"] == transport]
        out[transport] = {
            key: spread([r[key] for r in mine if r.get(key) is not None])
            for key in ("tracking_median", "ape_median")
        }
    out["tls_minus_plain"] = {}
    for key in ("tracking_median", "ape_median"):
        a, b = out["tls"][key]["median"], out["plain"][key]["median"]
        out["tls_minus_plain"][key] = None if a is None or b is None else a - b
    return out


# ============================================================================ output
def cell(s: dict[str, Any]) -> str:
    if s["median"] is None:
        return "-"
    return f"{s['median']:.3f} m ({s['min']:.3f}-{s['max']:.3f}), n={s['n']}"


def diff_cell(d: float | None) -> str:
    return "-" if d is None else f"{d:+.3f} m"


def table(result: dict[str, Any]) -> str:
    """The medians as a Markdown table."""
    m = result["medians"]
    lines = [
        f"Generated by `{result['command']}`.",
        "",
        "| transport | r2 tracking error median: median (min-max) | r2 APE median: median (min-max) |",
        "|---|---|---|",
    ]
    names = {"tls": "mutual TLS", "plain": "plain TCP"}
    for t in TRANSPORTS:
        lines.append(
            f"| {names[t]} | {cell(m[t]['tracking_median'])} | {cell(m[t]['ape_median'])} |"
        )
    d = m["tls_minus_plain"]
    lines.append(
        f"| TLS - plain | {diff_cell(d['tracking_median'])} | {diff_cell(d['ape_median'])} |"
    )
    return "\n".join(lines)


def write_markdown(path: Path, text: str) -> None:
    """``text`` between the markers of ``path``: replacing what was between them, else appended."""
    block = f"{BEGIN}\n{text}\n{END}"
    old = path.read_text() if path.exists() else ""
    start, end = old.find(BEGIN), old.find(END)
    if start >= 0 and end > start:
        new = old[:start] + block + old[end + len(END) :]
    elif start >= 0 or end >= 0:
        raise ValueError(f"{path}: one transport_ab marker without the other")
    else:
        new = old + ("\n" if old and not old.endswith("\n") else "") + block + "\n"
    path.write_text(new)


def fmt(v: float | None, unit: str) -> str:
    return "-" if v is None else f"{v:.3f} {unit}"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    command = shlex.join(["scripts/transport_ab.py", *(sys.argv[1:] if argv is None else argv)])
    team, secure = prepare(args.out)
    runs: list[dict[str, Any]] = []
    for i in range(args.runs):
        for transport in TRANSPORTS:
            run_dir = args.out / f"run{i:02d}-{transport}"
            code = drive(transport, run_dir, team, secure, args.seed, args.ape)
            run = {
                "index": i,
                "transport": transport,
                "dir": str(run_dir),
                **figures(run_dir, code, args.ape),
            }
            runs.append(run)
            print(f"run {i} {transport:5s}: tracking median {fmt(run['tracking_median'], 'm')}, "
                  f"APE median {fmt(run['ape_median'], 'm')}, released at {fmt(run.get('released_s'), 's')}"
                  + (f"  [{run['error']}]" if "error" in run else ""), flush=True)  # fmt: skip
    medians = summarise(runs)
    for transport in TRANSPORTS:
        print(f"{transport:5s}: tracking {cell(medians[transport]['tracking_median'])}; "
              f"APE {cell(medians[transport]['ape_median'])}")  # fmt: skip
    d = medians["tls_minus_plain"]
    print(
        f"TLS - plain: tracking {diff_cell(d['tracking_median'])}, APE {diff_cell(d['ape_median'])}"
    )
    result = {
        "command": command,
        "setup": {
            "seed": args.seed,
            "runs_per_transport": args.runs,
            "particles": PARTICLES,
            "path": str(PATH.relative_to(ROOT)),
            "robot": ROBOT,
            "ape": args.ape,
        },
        "runs": runs,
        "medians": medians,
    }
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    if args.markdown is not None:
        write_markdown(args.markdown, table(result))
    return 0 if all("error" not in r for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
