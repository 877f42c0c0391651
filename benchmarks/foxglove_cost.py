"""CPU cost of ``relloc serve --foxglove``: without a client, with one client, against none.

    .venv/bin/python benchmarks/foxglove_cost.py --bag ../shared/data/tiers/multi4_shortbag_20221011

The shortbag is replayed at ``--rate`` (2) into a serve subprocess, in three variants
interleaved ``--repeats`` times in the same run: plain serve, serve with ``--foxglove`` and no
client, serve with ``--foxglove`` and one WebSocket client (``tests/foxglove_client.py``)
subscribed to every channel. serve's CPU time (user + system, all threads) comes from
``wait4`` on its process; the ratios are against the plain runs' median. The client runs in
this process, so its own CPU is not counted.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from foxglove_client import FoxgloveClient  # noqa: E402

from relloc.live import free_tcp_port  # noqa: E402

CONFIG = REPO / "configs" / "tiers" / "multi4_shortbag_20221011.toml"
VARIANTS = ("plain", "foxglove", "foxglove+client")


def _wait(condition: Any, timeout: float) -> bool:
    end = time.time() + timeout
    while time.time() < end:
        if condition():
            return True
        time.sleep(0.02)
    return False


def run_once(bag: Path, variant: str, rate: float, tmp: Path) -> dict[str, Any]:
    """One serve of the replayed bag; its CPU seconds and what the client received."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    port = free_tcp_port()
    log = tmp / f"serve-{variant}.log"
    args = [sys.executable, "-m", "relloc.cli", "serve", "--config", str(CONFIG),
            "--clock-rate", str(rate), "--listen", endpoint, "--no-multicast"]  # fmt: skip
    if variant != "plain":
        args += ["--foxglove", f"127.0.0.1:{port}"]
    with log.open("wb") as fh:
        serve = subprocess.Popen(args, stdout=fh, stderr=subprocess.STDOUT, cwd=REPO)
    client = None
    try:
        if not _wait(lambda: "zenoh session" in log.read_text(), 120):
            raise RuntimeError(log.read_text())
        if variant == "foxglove+client":
            client = FoxgloveClient("127.0.0.1", port)
            if not _wait(lambda: bool(client.received("/relloc/status")), 60):
                raise RuntimeError(f"no status through Foxglove: {client.error}")
        replay = subprocess.run(
            [sys.executable, "-m", "relloc.cli", "replay", str(bag), "--config", str(CONFIG),
             "--rate", str(rate), "--connect", endpoint, "--no-multicast"],
            capture_output=True, text=True, cwd=REPO, timeout=300,
        )  # fmt: skip
        if replay.returncode != 0:
            raise RuntimeError(replay.stderr)
        serve.send_signal(signal.SIGTERM)
        _, status, usage = os.wait4(serve.pid, 0)
        serve.returncode = os.waitstatus_to_exitcode(status)
    finally:
        if client is not None:
            client.close()
        if serve.poll() is None:
            serve.kill()
            serve.wait()
    received = {}
    if client is not None:
        received = {t: len(client.received(t)) for t in sorted(client.topics())}
    return {"cpu_s": usage.ru_utime + usage.ru_stime, "received": received}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bag", type=Path, required=True)
    p.add_argument("--rate", type=float, default=2.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args()
    runs: dict[str, list[dict[str, Any]]] = {v: [] for v in VARIANTS}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeats):
            order = VARIANTS if i % 2 == 0 else VARIANTS[::-1]
            for variant in order:
                runs[variant].append(run_once(args.bag, variant, args.rate, Path(tmp)))
                print(f"{variant:16s} {runs[variant][-1]['cpu_s']:.2f} s CPU", flush=True)
    cpu = {v: statistics.median(r["cpu_s"] for r in rs) for v, rs in runs.items()}
    result = {
        "rate": args.rate,
        "repeats": args.repeats,
        "cpu_s": cpu,
        "ratio_no_client": cpu["foxglove"] / cpu["plain"],
        "ratio_one_client": cpu["foxglove+client"] / cpu["plain"],
        "received": runs["foxglove+client"][-1]["received"],
    }
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
