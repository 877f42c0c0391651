"""How relloc's particle-filter update scales with the particle count and the team size.

What is measured
----------------
One *update* of an N-robot team, as in ``benchmarks/filter_vs_pfilter.py``: the state is the
stacked positions of the N-1 non-reference robots relative to the reference (``D = 2(N-1)``
dimensions), and each update brings one odometry displacement per robot and the
``K = N(N-1)/2`` UWB ranges of all pairs::

    pf.predict(disp, sigma, dt)                          # odometry displacement + noise
    pf.update([RangeBatch(...)])                         # the K ranges, log-weights
    pf.estimate()                                        # weighted mean and covariance
    pf.resample()                                        # systematic, every step, 1 % re-drawn

with ``ParticleFilter(..., resample="every_step", reinject_fraction=0.01)``, the robots on a
3 m grid driving circles, the cloud started converged (0.3 m around the truth). Two sweeps:
over the particle count M at a fixed team (``--particles``, ``--robots-fixed``) and over the team
size at a fixed particle count (``--robots``, ``--particles-fixed``). Each point is the median of
``--reps`` timed updates after ``WARMUP`` untimed ones.

The references, measured in the same run, at every point:

- ``pass``: a plain NumPy pass over an ``(M, D)`` array the size of the state,
  ``x += y`` (read two arrays, write one): the cheapest thing an update over the particles can
  possibly do, with NumPy's own per-call overhead.
- ``floor``: the memory-traffic floor of the update, bytes touched / bandwidth. The bytes are
  what any implementation of this update must move at least once: the state read and written
  (predict), the ``(M, K)`` predicted ranges written and read (the likelihood), the state read
  again (estimate) and read and written (resample), and the log-weights: ``8 M (5 D + 2 K + 4)``
  bytes in float64. The bandwidth is that of a large copy (``np.copyto`` of ``--copy-mb`` MiB,
  larger than the caches), measured once at the start and reported.

The ratios ``update / pass`` and ``update / floor`` say how far the update is from what the
memory allows; they mean something on any machine, where the absolute times do not.

A third sweep times the large-team representation, :class:`relloc.estimators.range_graph.filter.RangeGraphFilter`
(what ``pf`` is for teams of ``LARGE_TEAM_ROBOTS`` and more, docs/explanation/scaling.md), over the same
team sizes: the same predict + update + estimate + ``maybe_resample`` (pruning) cycle with
``--hypotheses`` Gaussians (1: converged; 72: the start's orientation hypotheses), each started
0.3 m about the truth. Its cost does not depend on a particle count: ``H`` batched ``D x D``
solves and ``O(H K)`` for the ranges.
``--json FILE`` writes every point; ``--readme FILE`` writes the tables of the run (the particle
and team sweeps in section ``scaling``, the range-graph sweep in ``scaling_graph``) between the
markers of FILE (``relloc.evaluation.pages``).

Run it with relloc installed (no extra dependency)::

    python benchmarks/scaling.py                     # a subset, about a minute
    python benchmarks/scaling.py --full --json out/bench/scaling.json
    python benchmarks/scaling.py --full --readme benchmarks/README.md
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import platform
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from relloc.estimators.particle.filter import ParticleFilter
from relloc.estimators.range_graph.filter import RangeGraphFilter
from relloc.evaluation.pages import missing_section, write_between
from relloc.filter.base import WeightedFilter
from relloc.filter.motion import OdometryMotion
from relloc.filter.ranges import RangeBatch
from relloc.filter.state import StateLayout

FloatArray = NDArray[np.float64]

DT = 0.1  # s between updates
SPEED = 0.25  # m/s of every moving robot
SPACING = 3.0  # m between grid cells
SIGMA_ODOM = 0.02  # m per step, per robot and axis
PROCESS_NOISE = 0.03  # m/sqrt(s)
SIGMA_UWB = 0.15  # m
CLOUD_SPREAD = 0.3  # m
WARMUP = 2

DEFAULT_PARTICLES = (1_000, 10_000, 50_000)
DEFAULT_ROBOTS = (2, 5, 10, 20)
FULL_PARTICLES = (1_000, 5_000, 20_000, 50_000, 100_000, 200_000)
FULL_ROBOTS = (2, 5, 10, 20, 30, 50)


@dataclass(frozen=True)
class Team:
    """N robots on a grid (``r0`` static, the reference), the others driving circles."""

    layout: StateLayout
    pair_a: NDArray[np.intp]
    pair_b: NDArray[np.intp]
    centres: FloatArray  # (N, 2)
    phase: FloatArray  # (N,)
    omega: FloatArray  # (N,), 0 for the reference
    radius: float = 1.0

    def positions(self, k: int) -> FloatArray:
        angle = self.phase + self.omega * k * DT
        moving = (self.omega != 0.0)[:, None]
        ring = self.radius * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        return self.centres + np.where(moving, ring, 0.0)


def make_team(n: int, rng: np.random.Generator) -> Team:
    robots = tuple(f"r{i}" for i in range(n))
    cols = math.ceil(math.sqrt(n))
    centres = np.array(
        [[(k % cols) * SPACING, (k // cols) * SPACING] for k in range(n)], dtype=float
    )
    omega = np.full(n, SPEED / 1.0)
    omega[0] = 0.0
    pair_a, pair_b = (np.asarray(ix, dtype=np.intp) for ix in np.triu_indices(n, k=1))
    return Team(
        StateLayout(robots, "r0"), pair_a, pair_b, centres, rng.uniform(0, 2 * np.pi, n), omega
    )


def area_of(team: Team) -> tuple[float, float, float, float]:
    lo, hi = team.centres.min(axis=0) - 2.0, team.centres.max(axis=0) + 2.0
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


def _median_cycle(
    team: Team,
    f: WeightedFilter,
    resample: Callable[[], object],
    reps: int,
    rng: np.random.Generator,
) -> float:
    """Median seconds of one predict + update + estimate + ``resample`` of ``f`` on the team
    driving its circles, every pair ranging (the first ``WARMUP`` cycles not counted)."""
    n = len(team.layout.robots)
    k_pairs = len(team.pair_a)
    bias, sigma_uwb, sigma = np.zeros(k_pairs), np.full(k_pairs, SIGMA_UWB), np.full(n, SIGMA_ODOM)
    times = []
    for k in range(1, WARMUP + reps + 1):
        before, now = team.positions(k - 1), team.positions(k)
        disp = now - before + rng.normal(0.0, SIGMA_ODOM, (n, 2))
        ranges = np.linalg.norm(now[team.pair_a] - now[team.pair_b], axis=1) + rng.normal(
            0.0, SIGMA_UWB, k_pairs
        )
        batch = RangeBatch(team.pair_a, team.pair_b, ranges, bias, sigma_uwb)
        gc.collect()
        t0 = time.perf_counter()
        f.predict(disp, sigma, DT)
        f.update([batch])
        f.estimate()
        resample()
        if k > WARMUP:
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def time_update(team: Team, m: int, reps: int, seed: int) -> float:
    """Median seconds of one predict + update + estimate + resample at ``m`` particles."""
    rng = np.random.default_rng(seed)
    pf = ParticleFilter(
        team.layout,
        m,
        area_of(team),
        rng=np.random.default_rng(seed + 1),
        motion=OdometryMotion(process_noise=PROCESS_NOISE),
        resample="every_step",
        reinject_fraction=0.01,
    )
    start = team.positions(0)
    rel = (start[1:] - start[0]).reshape(-1)
    cloud = pf.particles.copy()
    cloud[:, : rel.size] = rel + rng.normal(0.0, CLOUD_SPREAD, (m, rel.size))
    pf.particles = cloud
    return _median_cycle(team, pf, pf.resample, reps, rng)


def time_graph_update(team: Team, hypotheses: int, reps: int, seed: int) -> float:
    """Median seconds of one predict + update + estimate + prune of the range-graph filter with
    ``hypotheses`` Gaussians (none is pruned: all start equally near the truth)."""
    rng = np.random.default_rng(seed)
    f = RangeGraphFilter(
        team.layout,
        area_of(team),
        rng=np.random.default_rng(seed + 1),
        motion=OdometryMotion(process_noise=PROCESS_NOISE),
    )
    start = team.positions(0)
    rel = (start[1:] - start[0]).reshape(-1)
    d = rel.size
    f.initialize(
        rel + rng.normal(0.0, CLOUD_SPREAD, (hypotheses, d)),
        np.repeat(np.eye(d)[None] * CLOUD_SPREAD**2, hypotheses, axis=0),
    )
    f.merge_distance = 0.0  # keep every hypothesis: the cost of H of them
    f.prune_weight = 0.0
    return _median_cycle(team, f, f.maybe_resample, reps, rng)


def time_pass(m: int, d: int, reps: int) -> float:
    """Median seconds of ``x += y`` over two ``(m, d)`` float64 arrays."""
    x, y = np.ones((m, d)), np.full((m, d), 1e-9)
    times = []
    for _ in range(reps + WARMUP):
        t0 = time.perf_counter()
        x += y
        times.append(time.perf_counter() - t0)
    return statistics.median(times[WARMUP:])


def copy_bandwidth(mib: int, reps: int = 5) -> float:
    """Bytes per second of ``np.copyto`` over ``mib`` MiB (read + write counted)."""
    src = np.ones(mib * 2**20 // 8)
    dst = np.empty_like(src)
    best = math.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        np.copyto(dst, src)
        best = min(best, time.perf_counter() - t0)
    return 2 * src.nbytes / best


def floor_bytes(m: int, d: int, k: int) -> int:
    """The bytes one update must move at least once (see the module docstring)."""
    return 8 * m * (5 * d + 2 * k + 4)


def measure(n: int, m: int, reps: int, bandwidth: float, seed: int) -> dict[str, float]:
    team = make_team(n, np.random.default_rng(seed))
    d, k = 2 * (n - 1), len(team.pair_a)
    update = time_update(team, m, reps, seed)
    plain = time_pass(m, d, reps)
    floor = floor_bytes(m, d, k) / bandwidth
    return {
        "robots": n,
        "particles": m,
        "dim": d,
        "pairs": k,
        "update_s": update,
        "pass_s": plain,
        "floor_s": floor,
        "update_over_pass": update / plain,
        "update_over_floor": update / floor,
    }


def _line(p: dict[str, float]) -> str:
    return (
        f"N={p['robots']:>3} M={p['particles']:>7}  D={p['dim']:>3} K={p['pairs']:>5}  "
        f"update {p['update_s'] * 1e3:9.2f} ms  pass {p['pass_s'] * 1e3:7.3f} ms  floor {p['floor_s'] * 1e3:7.3f} ms  "
        f"update/pass {p['update_over_pass']:6.1f}  update/floor {p['update_over_floor']:6.1f}"
    )


def _thousands(n: int) -> str:
    return f"{int(n):,}".replace(",", " ")


def sweep_table(points: Sequence[dict[str, float]], context: str) -> str:
    """The Markdown table of the particle and team sweeps (what ``--readme`` writes in section
    ``scaling``): every point in the order measured, a team-sweep point that repeats a
    particle-sweep one (same robots and particles) shown once, the first measured."""
    lines = [
        f"Written by {context}:",
        "",
        "| robots | particles | D | K | update | pass | floor | update / pass | update / floor |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    seen: set[tuple[int, int]] = set()
    for p in points:
        key = (int(p["robots"]), int(p["particles"]))
        if key in seen:
            continue
        seen.add(key)
        lines.append(
            f"| {int(p['robots'])} | {_thousands(int(p['particles']))} | {int(p['dim'])} | {int(p['pairs'])} | "
            f"{p['update_s'] * 1e3:.2f} ms | {p['pass_s'] * 1e3:.3f} ms | {p['floor_s'] * 1e3:.3f} ms | "
            f"{p['update_over_pass']:.0f} | {p['update_over_floor']:.0f} |"
        )
    return "\n".join(lines)


def graph_table(points: Sequence[dict[str, float]], context: str) -> str:
    """The Markdown table of the range-graph sweep (what ``--readme`` writes in section
    ``scaling_graph``)."""
    lines = [
        f"Written by {context}:",
        "",
        "| robots | hypotheses | D | K | update |",
        "|---:|---:|---:|---:|---:|",
    ]
    for p in points:
        lines.append(
            f"| {int(p['robots'])} | {int(p['hypotheses'])} | {int(p['dim'])} | {int(p['pairs'])} | "
            f"{p['update_s'] * 1e3:.2f} ms |"
        )
    return "\n".join(lines)


def command_options(args: argparse.Namespace) -> str:
    """The options of this run that change its figures, as they would be typed (``--full`` or not,
    ``--reps``, and every sweep or size option given away from its default)."""
    opts = ["--full"] if args.full else []
    if args.particles:
        opts.append("--particles " + " ".join(str(m) for m in args.particles))
    if args.robots:
        opts.append("--robots " + " ".join(str(n) for n in args.robots))
    if args.robots_fixed != 5:
        opts.append(f"--robots-fixed {args.robots_fixed}")
    if args.particles_fixed != 20_000:
        opts.append(f"--particles-fixed {args.particles_fixed}")
    opts.append(f"--reps {args.reps}")
    if args.copy_mb != 256:
        opts.append(f"--copy-mb {args.copy_mb}")
    if list(args.hypotheses) != [1, 72]:
        opts.append("--hypotheses " + " ".join(str(h) for h in args.hypotheses))
    if args.seed != 0:
        opts.append(f"--seed {args.seed}")
    return " ".join(opts)


def write_readme(path: Path, results: dict[str, object], args: argparse.Namespace) -> None:
    """Replace the sections ``scaling`` (and ``scaling_graph``, when that sweep ran) of ``path``
    with this run's tables."""
    bandwidth = float(results["bandwidth_bytes_per_s"])  # type: ignore[arg-type]
    context = (
        f"`benchmarks/scaling.py {command_options(args)} --readme` (numpy {np.__version__}, "
        f"Python {platform.python_version()}, {os.cpu_count()} CPUs; copy bandwidth "
        f"{bandwidth / 1e9:.1f} GB/s, read + write, {args.copy_mb} MiB)"
    )
    points = [*results["particles_sweep"], *results["robots_sweep"]]  # type: ignore[misc]
    write_between(path, "scaling", sweep_table(points, context))
    graph = results.get("graph_sweep") or []
    if graph:
        write_between(path, "scaling_graph", graph_table(graph, context))  # type: ignore[arg-type]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0] if __doc__ else None)
    parser.add_argument(
        "--particles",
        type=int,
        nargs="+",
        default=None,
        help=f"particle sweep (default {DEFAULT_PARTICLES})",
    )
    parser.add_argument(
        "--robots",
        type=int,
        nargs="+",
        default=None,
        help=f"team-size sweep (default {DEFAULT_ROBOTS})",
    )
    parser.add_argument(
        "--full",
        action="store_true",
        help=f"the full sweeps: particles {FULL_PARTICLES}, robots {FULL_ROBOTS}",
    )
    parser.add_argument(
        "--robots-fixed", type=int, default=5, help="team size of the particle sweep"
    )
    parser.add_argument(
        "--particles-fixed", type=int, default=20_000, help="particle count of the team sweep"
    )
    parser.add_argument("--reps", type=int, default=10, help="timed updates per point")
    parser.add_argument(
        "--copy-mb", type=int, default=256, help="MiB copied to measure the bandwidth"
    )
    parser.add_argument(
        "--hypotheses",
        type=int,
        nargs="+",
        default=[1, 72],
        help="Gaussians of the range-graph sweep",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="write every point to this file")
    parser.add_argument(
        "--readme",
        type=Path,
        help="write the tables into this Markdown file, between its scaling (and scaling_graph) figures markers",
    )
    args = parser.parse_args(argv)
    particles = args.particles or (FULL_PARTICLES if args.full else DEFAULT_PARTICLES)
    robots = args.robots or (FULL_ROBOTS if args.full else DEFAULT_ROBOTS)
    if min(robots) < 2 or args.robots_fixed < 2:
        parser.error("a team has at least 2 robots")

    problem = (
        None if args.readme is None else missing_section(args.readme, "scaling", "scaling_graph")
    )
    if problem is not None:
        parser.error(problem)

    bandwidth = copy_bandwidth(args.copy_mb)
    print(
        f"numpy {np.__version__}, Python {platform.python_version()}, {platform.machine()}; "
        f"copy bandwidth {bandwidth / 1e9:.2f} GB/s (read + write, {args.copy_mb} MiB)"
    )
    results: dict[str, object] = {
        "bandwidth_bytes_per_s": bandwidth,
        "particles_sweep": [],
        "robots_sweep": [],
    }
    print(f"-- over particles, {args.robots_fixed} robots")
    for m in particles:
        p = measure(args.robots_fixed, m, args.reps, bandwidth, args.seed)
        results["particles_sweep"].append(p)  # type: ignore[union-attr]
        print(_line(p), flush=True)
    print(f"-- over robots, {args.particles_fixed} particles")
    for n in robots:
        p = measure(n, args.particles_fixed, args.reps, bandwidth, args.seed)
        results["robots_sweep"].append(p)  # type: ignore[union-attr]
        print(_line(p), flush=True)
    print(f"-- range-graph Gaussian sum over robots, {args.hypotheses} hypotheses")
    results["graph_sweep"] = []
    for n in robots:
        team = make_team(n, np.random.default_rng(args.seed))
        for h in args.hypotheses:
            t = time_graph_update(team, h, args.reps, args.seed)
            point = {
                "robots": n,
                "hypotheses": h,
                "dim": 2 * (n - 1),
                "pairs": len(team.pair_a),
                "update_s": t,
            }
            results["graph_sweep"].append(point)  # type: ignore[union-attr]
            print(
                f"N={n:>3} H={h:>3}  D={point['dim']:>3} K={point['pairs']:>5}  update {t * 1e3:9.2f} ms",
                flush=True,
            )
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2) + "\n")
        print(f"wrote {args.json}")
    if args.readme is not None:
        write_readme(args.readme, results, args)
        print(f"wrote the figures into {args.readme}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
