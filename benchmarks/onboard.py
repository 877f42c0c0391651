"""A team of onboard estimators (``relloc serve --robot``) on Zenoh, one robot cut off a while.

    .venv/bin/python benchmarks/onboard.py --robots 4 --duration 30 --partition r1:10:20 --json F

N simulated robots (the ``grid`` scenario, the one that takes any N; seeded) each run as one
process: robot K's :class:`~relloc.live.LiveServer` with ``ServeOptions(robot=K)`` (what
``relloc serve --robot K`` runs, shipped defaults) and, on a thread of the same process and
Zenoh session, the publisher of K's own topics (its odometry, the ranges its node measures, each
at its simulated time on a shared clock), so these reach K's estimator without the network. The
robots are Zenoh peers on loopback, no scouting: each listens on its own port and connects to
every later robot through a TCP relay of this script, one per pair (a full mesh, every byte
between robots through a relay). The partition ``ROBOT:START:END`` is at the transport: from
START s the relays of ROBOT's links close both sockets and refuse new ones; Zenoh sees its links
drop, and from END s its retries (every 0.5 s) open them again: the serves never restart.

Measured, against the simulator's truth: per view (robot R's estimate of O, in R's body frame;
estimates in the formation frame are skipped and counted) the median position error
(``ape_median``) and the share of estimates whose 95 % ellipse holds the truth
(``coverage95``), with and without the partition; each serve process's CPU (% of a core, after
``--settle`` s, from ``/proc``) and peak RSS beside a bare Zenoh subscriber to the team's keys
over the same minutes, the part its robot's publisher thread took (``publisher_cpu_percent``),
the ratios to the bare subscriber of the process (``cpu_ratio``) and of the serve alone, the
process less that thread (``serve_cpu_ratio``: the robot's drivers' work is not the serve's),
and its RSS at the end as own memory and mapped files (``rss_anon_mb``, ``rss_file_mb``);
``partition_shift_m``: the largest distance between a view of one uncut robot by another at the
same stamp in the runs with and without the partition (same seed) over the partition;
``recovery_s``: the first time after END from which, for ``RECOVERY_HOLD`` s, every view of the
cut robot has its trailing 1 s median error within 0.02 m of the same view's median error
without the partition, minus END (``null``: never); the cut robot's ``hears`` show the cut took.
Live runs are not bit-repeatable (arrival order across processes): ``--floor`` adds a second
run without the partition, ``partition_shift_floor_m`` the same statistic between the two, and
``recovery_floor_s`` the recovery test on it (``null``: even a robot never cut is not "back"
by that test, its views' error moving more than 0.02 m about their median after END).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import math
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, cast

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/: the shared modules
import bare_subscriber

from relloc.live.resources import CpuSampler, proc_memory_mb, round_finite
from relloc.live.session import free_tcp_port

CHI2_95_2D = 5.991464547107979
"""The 95 % quantile of the chi-square distribution with two degrees of freedom."""
RECOVERY_TOL = 0.02
"""How close (m) to its median error a view must come back after the partition."""
RECOVERY_WINDOW = 1.0
"""Trailing window (s of stamps) of the running median error that must come back."""
RECOVERY_HOLD = 2.0
"""How long (s) every view of the cut robot must stay back for the recovery to count."""
RETRY_MS = 500
"""Zenoh's retry period for a lost link (ms)."""
TAIL = 1.5
"""Seconds a serve runs past the end of the stream (the last messages reach it)."""
STATUS_PERIOD = 0.5


@dataclass(frozen=True)
class Partition:
    """Robot ``robot`` cut off from ``start`` to ``end`` s of the run."""

    robot: str
    start: float
    end: float

    @classmethod
    def parse(cls, text: str) -> Partition:
        robot, start, end = text.split(":")
        p = cls(robot, float(start), float(end))
        if not 0.0 <= p.start < p.end:
            raise ValueError(f"--partition {text!r}: START < END expected")
        return p


@dataclass(frozen=True)
class Options:
    robots: int = 4
    duration: float = 30.0
    partition: Partition | None = None
    seed: int = 0
    settle: float = 5.0
    """CPU is measured from this many seconds after the first message."""
    floor: bool = False
    """With a partition, a second run without it: ``partition_shift_floor_m``."""
    kind: str = ""
    """The filter kind every serve runs (``[filter] kind``; empty: the team config's)."""
    reorder_window: float = 0.0
    """Every serve's reorder window (s; ``relloc serve --reorder-window``)."""


def team(robots: int, seed: int, duration: float, kind: str = "") -> tuple[Any, Any]:
    """The simulated team and the config its servers use (filter ``kind`` if given)."""
    from relloc.live.sim_robots import sim_team_config
    from relloc.simulator.scenarios import grid_scenario

    sim = grid_scenario(seed, robots=robots, duration=duration)
    config = sim_team_config(sim)
    if kind:
        config = replace(config, filter=replace(config.filter, kind=kind))
    return sim, config


def peer_config(listen: list[str], connect: list[str]) -> Any:
    """A Zenoh peer on explicit endpoints: no multicast, no gossip (no link the relays miss)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5(
        "connect/retry",
        json.dumps(
            {"period_init_ms": RETRY_MS, "period_max_ms": RETRY_MS, "period_increase_factor": 1.0}
        ),
    )
    return conf


# ---------------------------------------------------------------- the transport: relays
class Relay:
    """A TCP relay on loopback: what connects to :attr:`port` is joined to ``upstream``.

    :meth:`cut` closes every joined pair of sockets and refuses (accepts and closes) new
    connections until :meth:`heal`; bytes forwarded and accept times are counted."""

    def __init__(self, upstream: int) -> None:
        self.upstream = upstream
        self._server = socket.create_server(("127.0.0.1", 0))
        self.port: int = self._server.getsockname()[1]
        self._lock = threading.Lock()
        self._socks: list[socket.socket] = []
        self._cut = False
        self._closed = False
        self.bytes = 0
        self.accepted: list[float] = []
        self.refused = 0
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._server.accept()
            except OSError:
                return
            with self._lock:
                if self._cut or self._closed:
                    self.refused += 1
                    client.close()
                    continue
                try:
                    up = socket.create_connection(("127.0.0.1", self.upstream), timeout=5.0)
                except OSError:
                    client.close()
                    continue
                up.settimeout(None)
                self.accepted.append(time.time())
                self._socks += [client, up]
            for a, b in ((client, up), (up, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
                with self._lock:  # two pumps a link: no lost count
                    self.bytes += len(data)
        except OSError:
            pass
        for s in (src, dst):
            _shut(s)

    def cut(self) -> None:
        with self._lock:
            self._cut = True
            socks, self._socks = self._socks, []
        for s in socks:
            _shut(s)

    def heal(self) -> None:
        with self._lock:
            self._cut = False

    def close(self) -> None:
        with self._lock:
            self._closed = True
        self.cut()
        self._server.close()


def _shut(s: socket.socket) -> None:
    with contextlib.suppress(OSError):
        s.shutdown(socket.SHUT_RDWR)
    s.close()


class Mesh:
    """One :class:`Relay` per pair of robots: robot ``i`` connects to robot ``j > i`` through
    relay ``(i, j)``, which joins it to ``j``'s listening port."""

    def __init__(self, names: list[str], ports: list[int]) -> None:
        self.names = names
        self.ports = ports
        self.relays = {
            (a, b): Relay(ports[j])
            for i, a in enumerate(names)
            for j, b in enumerate(names)
            if i < j
        }

    def listen(self, robot: str) -> list[str]:
        return [f"tcp/127.0.0.1:{self.ports[self.names.index(robot)]}"]

    def connect(self, robot: str) -> list[str]:
        return [f"tcp/127.0.0.1:{r.port}" for (a, _), r in self.relays.items() if a == robot]

    def links(self, robot: str) -> list[Relay]:
        return [r for pair, r in self.relays.items() if robot in pair]

    def cut(self, robot: str) -> None:
        for r in self.links(robot):
            r.cut()

    def heal(self, robot: str) -> None:
        for r in self.links(robot):
            r.heal()

    def close(self) -> None:
        for r in self.relays.values():
            r.close()


# ---------------------------------------------------------------- one robot's process
class _Tap:
    """Stands in for the server's sink: passes everything on, keeps what the onboard view
    publishes (``[t, robot, frame_id, x, y, cxx, cxy, cyy, unseen_s]``) and each status
    (``[time, hears, messages received, those of them on the robot's own keys]``: both counted
    by the source, so their difference is exactly what came from the others).
    ``received`` gives the source's messages by key; ``own_keys`` are the keys the robot
    publishes on."""

    def __init__(
        self,
        sink: Any,
        time_base: list[float],
        received: Callable[[], dict[str, int]],
        own_keys: set[str],
    ) -> None:
        self._sink = sink
        self._time_base = time_base
        self._received = received
        self._own_keys = own_keys
        self.views: list[list[Any]] = []
        self.statuses: list[list[Any]] = []

    def __call__(self, est: Any) -> None:
        self._sink(est)
        est = est.published()
        for robot in est.positions:
            if robot == est.reference:
                continue
            x, y = (float(v) for v in est.position(robot)[:2])
            cov = est.covariance(robot)
            c = [math.nan] * 3 if cov is None else [cov[0, 0], cov[0, 1], cov[1, 1]]
            self.views.append(
                [est.t - self._time_base[0], robot, est.frame_id, x, y, *map(float, c),
                 est.unseen.get(robot)]
            )  # fmt: skip

    def publish_status(self, status: dict[str, Any]) -> None:
        self._sink.publish_status(status)
        own = sum(n for key, n in self._received().items() if key in self._own_keys)
        self.statuses.append([status["time"], status["hears"], status["source"]["messages"], own])

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sink, name)


def robot_process(spec: dict[str, Any]) -> int:
    """Robot ``spec["robot"]``: its onboard serve, and the publisher of its own topics."""
    import zenoh

    from relloc.events import measured_by
    from relloc.live import LiveServer, ServeOptions
    from relloc.live.publish import EventEncoder, Publishers
    from relloc.malloc import tune_malloc
    from relloc.sinks.zenoh_sink import ZenohSink

    tune_malloc()
    me = spec["robot"]
    sim, config = team(spec["robots"], spec["seed"], spec["duration"], spec["kind"])
    own = [ev for ev in sim.events() if measured_by(ev, me)]
    session = zenoh.open(peer_config(spec["listen"], spec["connect"]))
    server = LiveServer(
        config,
        session,
        ServeOptions(
            robot=me,
            seed=spec["seed"],
            status_period=STATUS_PERIOD,
            keep_estimates=50,
            reorder_window=spec["reorder_window"],
        ),
    )
    time_base = [0.0]
    sent = [0]
    own_keys: set[str] = set()  # added to before a message goes out on one
    tap = _Tap(server.sink, time_base, lambda: dict(server.source.stats.messages), own_keys)
    server.sink = cast(ZenohSink, tap)
    pubs = Publishers(session, node=f"{me}_robot")
    encoder = EventEncoder(config)
    stop = threading.Event()

    publisher_cpu: list[tuple[float, float]] = []  # (wall, thread CPU) at most every 0.5 s

    def publish() -> None:
        for ev in own:
            if stop.wait(max(0.0, time_base[0] + ev.t - time.time())):
                return
            out = encoder.encode(ev, time_base[0])
            if out is not None:
                own_keys.add(out[0].topic_key)
                pubs.put(*out)
                sent[0] += 1
            now = time.time()
            if not publisher_cpu or now - publisher_cpu[-1][0] >= 0.5:
                publisher_cpu.append((now, time.thread_time()))

    try:
        server.start()
        gc.collect()
        gc.freeze()
        print("ready", flush=True)
        time_base[0] = float(sys.stdin.readline().split()[1])
        publisher = threading.Thread(target=publish, name="publisher", daemon=True)
        publisher.start()
        summary = server.run(time_base[0] + spec["duration"] + TAIL - time.time())
        stop.set()
        publisher.join(timeout=5)
    finally:
        server.close()
        pubs.close()
        session.close()
    out = {
        "robot": me,
        "published": sent[0],
        "received": summary["source"]["messages"],
        "engine_errors": summary["engine_errors"],
        "views": tap.views,
        "statuses": tap.statuses,
        "publisher_cpu": publisher_cpu,
    }
    Path(spec["out"]).write_text(json.dumps(out))
    return 0


# ---------------------------------------------------------------- scoring
def body_truth(sim: Any, me: str, other: str, t: np.ndarray) -> np.ndarray:
    """``other``'s true position in ``me``'s body frame at times ``t``: ``(n, 2)``."""
    p0, p1 = sim.true_poses(me, t), sim.true_poses(other, t)
    d = p1[:, :2] - p0[:, :2]
    c, s = np.cos(p0[:, 2]), np.sin(p0[:, 2])
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])


def body_rows(rows: list[list[Any]], me: str) -> dict[str, np.ndarray]:
    """The body-frame rows of one robot's views by teammate: ``(n, 6)`` of
    ``t, x, y, cxx, cxy, cyy``, sorted by stamp."""
    out: dict[str, list[list[float]]] = {}
    for t, other, frame, x, y, cxx, cxy, cyy, _ in rows:
        if frame == f"{me}/base_link":
            out.setdefault(other, []).append([t, x, y, cxx, cxy, cyy])
    return {o: np.array(sorted(v)) for o, v in sorted(out.items())}


def errors(sim: Any, me: str, other: str, view: np.ndarray) -> np.ndarray:
    """Position errors (m) of the rows ``view`` of ``me``'s view of ``other``."""
    return np.hypot(*(view[:, 1:3] - body_truth(sim, me, other, view[:, 0])).T)


def score_views(sim: Any, me: str, rows: list[list[Any]]) -> dict[str, Any]:
    """``ape_median`` and ``coverage95`` of each of ``me``'s views; ``formation_skipped``."""
    out: dict[str, Any] = {}
    for other, v in body_rows(rows, me).items():
        d = v[:, 1:3] - body_truth(sim, me, other, v[:, 0])
        cov = np.stack([v[:, [3, 4]], v[:, [4, 5]]], axis=1)
        ok = np.all(np.isfinite(cov), axis=(1, 2))
        m2 = np.einsum("ni,nij,nj->n", d[ok], np.linalg.inv(cov[ok]), d[ok])
        out[other] = {
            "ape_median": round(float(np.median(np.hypot(*d.T))), 4),
            "coverage95": round(float(np.mean(m2 <= CHI2_95_2D)), 4) if ok.any() else None,
            "n": len(v),
        }
    out["formation_skipped"] = sum(1 for r in rows if r[2] != f"{me}/base_link")
    return out


def partition_shift(
    with_cut: dict[str, list[list[Any]]],
    without: dict[str, list[list[Any]]],
    partition: Partition,
) -> dict[str, Any]:
    """How far the uncut robots' views of each other moved, stamp by stamp, over the partition."""
    shifts: list[float] = []
    for me in with_cut:
        if me == partition.robot:
            continue
        a, b = body_rows(with_cut[me], me), body_rows(without[me], me)
        for other in a.keys() & b.keys() - {partition.robot}:
            ref = {round(t, 3): (x, y) for t, x, y, *_ in b[other]}
            for t, x, y, *_ in a[other]:
                xy = ref.get(round(t, 3))
                if xy is not None and partition.start <= t <= partition.end:
                    shifts.append(math.hypot(x - xy[0], y - xy[1]))
    if not shifts:
        return {"max_m": None, "median_m": None, "n": 0}
    return {
        "max_m": round(max(shifts), 4),
        "median_m": round(float(np.median(shifts)), 4),
        "n": len(shifts),
    }


def running_median(t: np.ndarray, e: np.ndarray, window: float) -> np.ndarray:
    """The median of ``e`` over the trailing ``window`` s of stamps ``t`` (sorted), at each row."""
    lo = np.searchsorted(t, t - window, side="left")
    return np.array([np.median(e[i : k + 1]) for k, i in enumerate(lo)])


def recovery(
    sim: Any,
    cut_rows: list[list[Any]],
    medians: dict[str, float],
    partition: Partition,
    duration: float,
) -> dict[str, Any]:
    """``recovery_s`` (module docstring) of the cut robot's views, ``medians`` their median
    errors without the partition; the moments at which each view was last out."""
    me = partition.robot
    views = body_rows(cut_rows, me)
    out_at: list[float] = []  # stamps after END at which some view was out
    for other, level in medians.items():
        v = views.get(other)
        if v is None or not len(v):
            return {"recovery_s": None, "why": f"no view of {other}"}
        smooth = running_median(v[:, 0], errors(sim, me, other, v), RECOVERY_WINDOW)
        after = v[:, 0] >= partition.end
        out_at += v[after & (smooth > level + RECOVERY_TOL), 0].tolist()
    # the first t >= END such that no view is out in [t, t + HOLD]
    candidates = [partition.end] + [t + 1e-6 for t in sorted(out_at)]
    horizon = min(duration, partition.end + 1e9)
    for t in candidates:
        if t + RECOVERY_HOLD > horizon:
            break
        if not any(t <= s <= t + RECOVERY_HOLD for s in out_at):
            return {"recovery_s": round(t - partition.end, 3)}
    return {"recovery_s": None, "why": "not back for long enough before the end of the run"}


# ---------------------------------------------------------------- one run of the team
def _read_line(proc: subprocess.Popen[str], timeout: float) -> str:
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    return proc.stdout.readline().strip() if ready else ""


def _sleep_until(t: float) -> None:
    time.sleep(max(0.0, t - time.time()))


def run_team(
    opts: Options, partition: Partition | None, bare: bool, workdir: Path, tag: str
) -> dict[str, Any]:
    """One run: N robot processes (and the bare subscriber), the partition if any."""
    _, config = team(opts.robots, opts.seed, opts.duration)
    names = list(config.robot_names)
    mesh = Mesh(names, [free_tcp_port() for _ in names])
    procs: dict[str, subprocess.Popen[str]] = {}
    logs = []
    bare_proc: subprocess.Popen[str] | None = None
    samplers: dict[str, CpuSampler] = {}
    result: dict[str, Any] = {}
    try:
        for me in names:
            spec = {
                "robot": me, "robots": opts.robots, "seed": opts.seed, "duration": opts.duration,
                "kind": opts.kind, "reorder_window": opts.reorder_window,
                "listen": mesh.listen(me), "connect": mesh.connect(me),
                "out": str(workdir / f"{tag}_{me}.json"),
            }  # fmt: skip
            logs.append((workdir / f"{tag}_{me}.log").open("w"))
            procs[me] = subprocess.Popen(
                [sys.executable, __file__, "--robot-process", json.dumps(spec)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=logs[-1], text=True,
            )  # fmt: skip
        if bare:
            from relloc.sources.zenoh_source import ZenohSource

            # a peer connected to every robot, listening nowhere, no gossip: it joins no one
            endpoints = [e for me in names for e in mesh.listen(me)]
            exprs = ZenohSource(config).expressions
            bare_proc = bare_subscriber.start(endpoints, exprs, listen=[], gossip=False)
        waiting = list(procs.items())
        if bare_proc is not None:
            waiting.append(("bare", bare_proc))
        for name, proc in waiting:
            if _read_line(proc, 120.0) != "ready":
                raise RuntimeError(f"{name} did not start; see {workdir}/{tag}_{name}.log")
        time_base = float(math.ceil(time.time() + 1.0))
        for p in procs.values():
            assert p.stdin is not None
            p.stdin.write(f"go {time_base}\n")
            p.stdin.flush()
        samplers = {me: CpuSampler(p.pid) for me, p in procs.items()}
        if bare_proc is not None:
            samplers["bare"] = CpuSampler(bare_proc.pid)
        if partition is not None:
            cut_links = mesh.links(partition.robot)
            _sleep_until(time_base + partition.start)
            mesh.cut(partition.robot)
            cut_at = time.time()
            bytes_at_cut = sum(r.bytes for r in cut_links)
            _sleep_until(time_base + partition.end)
            bytes_during = sum(r.bytes for r in cut_links) - bytes_at_cut
            mesh.heal(partition.robot)
            healed_at = time.time()
            result["partition"] = {
                "robot": partition.robot,
                "start_s": partition.start,
                "end_s": partition.end,
                "cut_at_s": round(cut_at - time_base, 3),
                "healed_at_s": round(healed_at - time_base, 3),
                "relay_bytes_during": bytes_during,
                "refused_during": sum(r.refused for r in cut_links),
            }
        t_end = time_base + opts.duration
        _sleep_until(t_end)
        t0 = time_base + opts.settle
        cpu, rss, own, files = {}, {}, {}, {}
        for me, p in procs.items():
            samplers[me].stop()
            cpu[me] = round_finite(samplers[me].percent_between(t0, t_end), 2)
            mem = proc_memory_mb(p.pid)
            rss[me] = round(mem.get("VmHWM", math.nan), 1)
            own[me] = round(mem.get("RssAnon", math.nan), 1)
            files[me] = round(mem.get("RssFile", math.nan), 1)
        result.update({"cpu_percent": cpu, "rss_mb": rss})
        result.update({"rss_anon_mb": own, "rss_file_mb": files})
        if bare_proc is not None:
            samplers["bare"].stop()
            result["bare_cpu_percent"] = round_finite(
                samplers["bare"].percent_between(t0, t_end), 2
            )
            result["bare_rss_mb"] = round(proc_memory_mb(bare_proc.pid).get("VmHWM", math.nan), 1)
        for me, p in procs.items():
            if p.wait(timeout=60) != 0:
                raise RuntimeError(f"{me} failed; see {workdir}/{tag}_{me}.log")
        robots = {me: json.loads((workdir / f"{tag}_{me}.json").read_text()) for me in names}
        result["robots"] = robots
        result["time_base"] = time_base
        result["publisher_cpu_percent"] = {
            me: _thread_percent(robots[me]["publisher_cpu"], t0, t_end) for me in names
        }
        if partition is not None and "partition" in result:
            _partition_checks(result, robots, partition, time_base)
    finally:
        for s in samplers.values():
            s.stop()
        for child in [*procs.values(), bare_proc]:
            if child is not None and child.poll() is None:
                child.send_signal(signal.SIGTERM)
                try:
                    child.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    child.kill()
                    child.wait()
        for fh in logs:
            fh.close()
        mesh.close()
    if partition is not None and "partition" in result:
        healed = time_base + result["partition"]["healed_at_s"]
        again = [t for r in mesh.links(partition.robot) for t in r.accepted if t >= healed]
        result["partition"]["rejoined_after_s"] = (
            round(max(again) - healed, 3)
            if len(again) >= len(mesh.links(partition.robot))
            else None
        )
    return result


def _thread_percent(samples: list[list[float]], t0: float, t1: float) -> float | None:
    """A thread's CPU (% of a core) from ``t0`` to ``t1`` out of its ``(wall, thread CPU)``
    samples: between the last samples at or before each (``None``: too few)."""
    before = [s for s in samples if s[0] <= t0]
    upto = [s for s in samples if s[0] <= t1]
    if not before or not upto or upto[-1][0] <= before[-1][0]:
        return None
    (w0, c0), (w1, c1) = before[-1], upto[-1]
    return round_finite(100.0 * (c1 - c0) / (w1 - w0), 2)


def _partition_checks(
    result: dict[str, Any], robots: dict[str, Any], partition: Partition, time_base: float
) -> None:
    """Whom each robot heard while the partition had been on for longer than serve's 2 s
    ``quiet_after`` (its status: a robot counts as heard from the ranges it is named in, so the
    cut robot still hears those its own node measures), and how many messages the cut robot
    received meanwhile beyond its own (none, if the partition took)."""
    lo = time_base + result["partition"]["cut_at_s"] + 2.0 + STATUS_PERIOD
    hi = time_base + result["partition"]["healed_at_s"]
    hears: dict[str, list[str]] = {}
    for me, r in robots.items():
        during = [s for s in r["statuses"] if lo <= s[0] <= hi]
        hears[me] = sorted({h for s in during for h in s[1]})
    cut = [s for s in robots[partition.robot]["statuses"] if lo <= s[0] <= hi]
    result["partition"]["hears_during"] = hears
    result["partition"]["statuses_during"] = len(cut)
    result["partition"]["cut_robot_foreign_messages_during"] = (
        (cut[-1][2] - cut[0][2]) - (cut[-1][3] - cut[0][3]) if len(cut) >= 2 else None
    )


# ---------------------------------------------------------------- the benchmark
def run(opts: Options, workdir: Path, say: Any = print) -> dict[str, Any]:
    """The run without the partition, then (if any) the run with it; the figures."""
    sim, config = team(opts.robots, opts.seed, opts.duration)
    names = list(config.robot_names)
    if opts.partition is not None and opts.partition.robot not in names:
        raise ValueError(f"--partition: {opts.partition.robot!r} is not one of {names}")
    say(f"{opts.robots} robots, {opts.duration:g} s: the run without the partition")
    base = run_team(opts, None, True, workdir, "base")
    base_views = {me: score_views(sim, me, base["robots"][me]["views"]) for me in names}
    out: dict[str, Any] = {
        "scenario": f"grid, {opts.robots} robots, seed {opts.seed}",
        "filter_kind": opts.kind or config.filter.kind,
        "reorder_window_s": opts.reorder_window,
        "robots": opts.robots,
        "duration_s": opts.duration,
        "settle_s": opts.settle,
        "views": {
            me: {o: v for o, v in vs.items() if o != "formation_skipped"}
            for me, vs in base_views.items()
        },
        "formation_skipped": {me: vs["formation_skipped"] for me, vs in base_views.items()},
        "cpu_percent": base["cpu_percent"],
        "publisher_cpu_percent": base["publisher_cpu_percent"],
        "rss_mb": base["rss_mb"],
        "rss_anon_mb": base["rss_anon_mb"],
        "rss_file_mb": base["rss_file_mb"],
        "bare_cpu_percent": base.get("bare_cpu_percent"),
        "bare_rss_mb": base.get("bare_rss_mb"),
        "messages": {
            me: {k: base["robots"][me][k] for k in ("published", "received", "engine_errors")}
            for me in names
        },
    }
    bare_cpu = out["bare_cpu_percent"]
    if bare_cpu:
        out["cpu_ratio"] = {
            me: round_finite(c / bare_cpu, 2) if c is not None else None
            for me, c in out["cpu_percent"].items()
        }
        out["serve_cpu_ratio"] = {
            me: round_finite((c - out["publisher_cpu_percent"][me]) / bare_cpu, 2)
            if c is not None and out["publisher_cpu_percent"].get(me) is not None
            else None
            for me, c in out["cpu_percent"].items()
        }
    say(_line(out))
    if opts.partition is None:
        return out
    p = opts.partition
    say(f"the run with {p.robot} cut off from {p.start:g} to {p.end:g} s")
    cut = run_team(opts, p, False, workdir, "cut")
    cut_views = {me: score_views(sim, me, cut["robots"][me]["views"]) for me in names}
    out["views_partitioned"] = {
        me: {o: v for o, v in vs.items() if o != "formation_skipped"}
        for me, vs in cut_views.items()
    }
    out["cpu_percent_partitioned"] = cut["cpu_percent"]
    out["rss_mb_partitioned"] = cut["rss_mb"]
    out["partition"] = cut["partition"]
    shift = partition_shift(_views(cut), _views(base), p)
    out["partition_shift_m"] = shift["max_m"]
    out["partition_shift"] = shift
    if opts.floor:
        say("a second run without the partition: what arrival order alone moves")
        again = run_team(opts, None, False, workdir, "again")
        floor = partition_shift(_views(again), _views(base), p)
        out["partition_shift_floor_m"] = floor["max_m"]
        out["partition_shift_floor"] = floor
        say(f"between two runs without it, over the same seconds: up to {floor['max_m']} m "
            f"(median {floor['median_m']})")  # fmt: skip
    medians = {o: v["ape_median"] for o, v in out["views"][p.robot].items()}
    rec = recovery(sim, cut["robots"][p.robot]["views"], medians, p, opts.duration)
    out["recovery_s"] = rec["recovery_s"]
    out["recovery"] = rec
    if opts.floor:  # the same test on the run that had no partition: what the data allow
        again_rec = recovery(sim, again["robots"][p.robot]["views"], medians, p, opts.duration)
        out["recovery_floor_s"] = again_rec["recovery_s"]
        out["recovery_floor"] = again_rec
    say(
        f"partition: {p.robot} heard {out['partition']['hears_during'][p.robot]} during it, "
        f"rejoined {out['partition']['rejoined_after_s']} s after; the others' views of each "
        f"other moved by up to {shift['max_m']} m (median {shift['median_m']}, n={shift['n']}); "
        f"{p.robot}'s views back after {out['recovery_s']} s"
    )
    return out


def _views(team_run: dict[str, Any]) -> dict[str, list[list[Any]]]:
    """Each robot's view rows in a :func:`run_team` result."""
    return {me: r["views"] for me, r in team_run["robots"].items()}


def _line(out: dict[str, Any]) -> str:
    apes = [v["ape_median"] for vs in out["views"].values() for v in vs.values()]
    covs = [
        v["coverage95"]
        for vs in out["views"].values()
        for v in vs.values()
        if v["coverage95"] is not None
    ]
    views = (
        f"views: APE median {min(apes):.3f}-{max(apes):.3f} m, coverage95 "
        f"{min(covs):.0%}-{max(covs):.0%}"
        if apes and covs
        else "views: none in a body frame"
    )
    return (
        f"{views}; serve CPU {out['cpu_percent']} % of a core, bare "
        f"{out['bare_cpu_percent']} % (of serve's, its process's publisher of the robot's own "
        f"topics {out['publisher_cpu_percent']} %)"
        + (f", the serve alone {out['serve_cpu_ratio']}x bare" if "serve_cpu_ratio" in out else "")
        + f"; peak RSS {out['rss_mb']} MB (at the end {out['rss_anon_mb']} own + "
        f"{out['rss_file_mb']} mapped files)"
    )


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.robot_process is not None:
        return robot_process(json.loads(args.robot_process))
    try:
        partition = Partition.parse(args.partition) if args.partition else None
    except ValueError as exc:
        print(f"onboard.py: {exc}", file=sys.stderr)
        return 2
    if partition is not None and partition.end >= args.duration:
        print("onboard.py: the partition must end before the run does", file=sys.stderr)
        return 2
    opts = Options(
        args.robots, args.duration, partition, args.seed, args.settle, args.floor, args.kind,
        args.reorder_window,
    )  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="relloc-onboard-") as tmp:
        out = run(opts, Path(tmp))
    out["context"] = f"Python {sys.version.split()[0]}, {os.cpu_count()} CPUs"
    if args.json_path is not None:
        args.json_path.parent.mkdir(parents=True, exist_ok=True)
        args.json_path.write_text(json.dumps(out, indent=1))
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description="A team of onboard estimators, one robot cut off.")
    p.add_argument("--robots", type=int, default=4)
    p.add_argument("--duration", type=float, default=30.0, help="simulated seconds (real time)")
    p.add_argument("--partition", default=None, metavar="ROBOT:START:END")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--settle", type=float, default=5.0, help="CPU measured after S s")
    p.add_argument(
        "--floor",
        action="store_true",
        help="with --partition: a second run without it, for partition_shift_floor_m",
    )
    p.add_argument("--kind", default="", help="the serves' filter kind (default: the config's)")
    p.add_argument(
        "--reorder-window", type=float, default=0.0, help="every serve's reorder window (s)"
    )
    p.add_argument("--json", dest="json_path", type=Path, default=None, metavar="FILE")
    p.add_argument("--robot-process", default=None, help=argparse.SUPPRESS)
    return p


if __name__ == "__main__":
    sys.exit(main())
