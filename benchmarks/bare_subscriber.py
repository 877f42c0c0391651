"""The bare Zenoh subscriber the serve benchmarks measure relloc against.

A peer process that subscribes to the same key expressions as the serve under test, with a
callback that only counts (it imports only ``zenoh``): what receiving the stream costs at all.
``serve_vs_subscriber.py`` connects it to its publisher's one endpoint; ``onboard.py`` to every
robot's, listening nowhere and without gossip (so that it joins no robot to another). It prints
``ready`` once subscribed and, on SIGTERM, the number of samples it received.
"""

from __future__ import annotations

import json
import subprocess
import sys

SCRIPT = """
import json, signal, sys, threading, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
for key, value in json.loads(sys.argv[1]).items():
    conf.insert_json5(key, json.dumps(value))
session = zenoh.open(conf)
count = [0]
def on_sample(sample):
    count[0] += 1
subs = [session.declare_subscriber(expr, on_sample) for expr in sys.argv[2:]]
done = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: done.set())
print("ready", flush=True)
done.wait()
print(count[0], flush=True)
"""
"""Run with ``python -c``: argv[1] the Zenoh config entries (JSON), then the key expressions."""


def start(
    connect: list[str],
    expressions: list[str],
    *,
    listen: list[str] | None = None,
    gossip: bool = True,
) -> subprocess.Popen[str]:
    """Start the bare subscriber, a peer connected to ``connect`` without multicast scouting;
    ``listen``: its own endpoints (``None``: Zenoh's default), ``gossip``: whether it gossips.
    Its stdout is a pipe: read ``ready`` from it before publishing, and :func:`received` after
    SIGTERM."""
    entries: dict[str, object] = {"connect/endpoints": list(connect)}
    if listen is not None:
        entries["listen/endpoints"] = list(listen)
    entries["scouting/multicast/enabled"] = False
    if not gossip:
        entries["scouting/gossip/enabled"] = False
    return subprocess.Popen(
        [sys.executable, "-c", SCRIPT, json.dumps(entries), *expressions],
        stdout=subprocess.PIPE,
        text=True,
    )


def received(stdout: str) -> int | None:
    """The sample count the subscriber printed last (``None``: it printed none)."""
    words = stdout.split()
    return int(words[-1]) if words else None
