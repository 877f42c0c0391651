"""relloc's particle filter versus the research reference built on ``pfilter``, per update.

What is measured
----------------
One *update* of a 5-robot team: the state is the stacked positions of the 4 non-reference
robots relative to the reference (8 dimensions), and each update brings one odometry
displacement per robot and the 10 UWB ranges of all robot pairs. For each particle count
``M`` (400, 4 000, 40 000 by default) both filters start from the same particle cloud (a
converged cloud around the true formation: 0.3 m spread) and then consume the same sequence
of simulated steps, alternating which implementation runs first on each step so that machine
noise (frequency scaling, other processes, caches) hits both alike. The wall-clock time of
every update is recorded with ``time.perf_counter``; a few untimed warm-up updates come first.
The report is the median per update of each implementation and the ratio
``pfilter / relloc`` (the speed-up of relloc). On a busy shared machine a long update is
pre-empted many times and its wall time swings from run to run; ``--clock cpu`` records the
process's CPU time instead (``time.process_time``, all threads, so pfilter's BLAS threads
count too), which such a machine disturbs far less. A median RMS position error of each
filter is printed beside the times as a check that both really track the team.

relloc, one update::

    pf.predict(disp, sigma, dt)                          # odometry displacement + noise
    pf.update([RangeBatch(...)])                         # the 10 ranges, log-weights
    est = pf.estimate()                                  # the dominant mode's mean and covariance
    est.summary.shape, est.summary.distances             # what a published estimate carries
    pf.resample()                                        # systematic, every step, 1 % re-drawn

with ``ParticleFilter(..., resample="every_step", reinject_fraction=0.01)``.

The reference, one update: ``pfilter.ParticleFilter.update(ranges, odom=...)`` configured as
the paper describes its research code and as the ``pfilter`` README documents the API
(pfilter 0.2.5, see ``benchmarks/requirements-pfilter.txt``): ``prior_fn`` uniform over the
same prior box, ``dynamics_fn`` adds the odometry displacement of every robot relative to
the reference, ``noise_fn`` is pfilter's ``gaussian_noise``, ``observe_fn`` maps particles to
the 10 predicted ranges, ``weight_fn`` is pfilter's ``squared_error`` helper (a Gaussian RBF
kernel of the squared range error), ``resample_proportion=0.01`` and the default
``n_eff_threshold=1.0`` (resampling at every step). Every user function is written
*vectorised*, ``(M, 8) -> (M, 10)`` and ``((M, 10), (1, 10)) -> (M,)``: that is the
contract of pfilter 0.2.x (and already of 0.1; the README's own ``blob`` example only loops
because it draws images). ``update`` passes its keyword arguments on to every user function,
which is how the odometry reaches ``dynamics_fn``. The resampling function is pfilter's
default (``resample_fn`` not given, as in the README), which in 0.2.5 is the SciPy-cookbook
``resample``: it builds the cumulative sum with one ``np.sum`` per particle (quadratic in M)
and walks it in a Python loop. ``--pfilter-resample systematic`` passes pfilter's own
``systematic_resample`` instead (a linear-time Python loop), to show how much of the gap is
that default.

What differs (all of it, to our knowledge)
------------------------------------------
- Range likelihood: relloc uses its symmetric model, a Gaussian-plus-uniform mixture per
  range with a per-pair bias (the model of an uncalibrated pair; the shipped config gives
  calibrated ranges the NLOS-aware mixture, which ``--phases`` times beside, dearer still);
  pfilter uses a plain Gaussian kernel ``exp(-sum err^2 / 2 sigma^2)`` in linear space.
  relloc does more arithmetic here.
- Odometry noise: relloc draws each robot's noise and, once per particle, the reference
  robot's noise shared by all relative positions (8 + 2 normals per particle); pfilter adds
  diagonal noise with the combined standard deviation (8 normals per particle).
- Re-injection from the prior: relloc replaces exactly ``round(0.01 M)`` particles chosen
  without replacement; pfilter replaces a Bernoulli(0.01) subset, and draws a full
  ``M``-particle prior sample to do it (that is how ``init_filter(mask)`` works).
- Estimate: relloc's timed step includes everything a published estimate carries (the
  summary of :mod:`relloc.filter.summary`: modes, the dominant mode's mean and covariance,
  the shape in its gauge and the pairwise distances; ``--estimate moments`` stops at the mode's
  mean and covariance, what a step nobody publishes computes); pfilter computes the weighted
  mean and covariance of all particles, and also, inside
  ``update``, its MAP particle, mean hypothesis, weight entropy and effective sample size,
  which it always does. relloc's ``estimate`` also returns the effective sample size.
- Weights: relloc keeps log-weights; pfilter linear weights.
- Prior: pfilter gets a plain NumPy uniform ``prior_fn`` rather than the README's
  ``independent_sample`` of ``scipy.stats`` distributions, which would only be slower.
- Random numbers: relloc's predict draws its odometry noise from a compiled stream (a
  ziggurat over SplitMix64, seeded each step from its ``numpy.random.Generator``, which draws
  everything else); pfilter uses the legacy global ``numpy.random`` state (seeded).
- Compiled code: relloc's step runs as a few passes compiled by ``numba`` (predict, range
  likelihood, normalisation, summary, resampling; compiled once and cached on disk, the
  compilation outside the timed updates), pfilter's is NumPy and Python.
- Predicted ranges: both gather the two robots of every pair and take the norm of the
  difference: relloc in its compiled likelihood over blocks of particles turned into
  coordinate planes, the reference in ``observe_fn`` over an ``(M, N, 2)`` array, as a pfilter
  user would naturally write it.
- Repetitions: ``--reps`` timed updates (default 40) per implementation at every M, except
  pfilter at M >= 40 000 with its default resampler, which runs ``--reps-large`` (default 20)
  because one of its updates takes about half a second there; relloc still runs ``--reps``,
  and the two are interleaved for as long as both have repetitions left.
- Allocator: with ``--malloc tuned`` (the default) glibc keeps freed memory mapped, as the
  ``relloc`` command sets it (:mod:`relloc.malloc`); process-wide, so for both. With glibc's
  own adaptive thresholds whether a step's temporaries fault in fresh pages depends on the
  order of its allocations, and relloc's time at 40 000 particles swings by a third between
  otherwise equal versions of the code.
- Threads: neither side sets a thread count; only pfilter's ``np.cov`` reaches BLAS (which
  may use several threads), relloc's arithmetic is single-threaded.

Run it in the benchmark environment (pfilter is not a dependency of relloc)::

    python -m venv .venv-bench
    .venv-bench/bin/pip install -e . -r benchmarks/requirements-pfilter.txt
    .venv-bench/bin/python benchmarks/filter_vs_pfilter.py --json out/bench.json

or ``make bench``.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import os
import platform
import statistics
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib.metadata import version as dist_version
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from relloc.estimators.particle.filter import ParticleFilter
from relloc.evaluation.pages import markers, write_between
from relloc.filter.motion import OdometryMotion, standard_normal
from relloc.filter.ranges import GROSS_FRACTION, NLOS_FRACTION, NLOS_SIGMA, RangeBatch
from relloc.filter.state import StateLayout
from relloc.malloc import tune_malloc

FloatArray = NDArray[np.float64]

SETUP_HINT = """pfilter is not installed in this environment. It is not a dependency of relloc; the
benchmark has an environment of its own:

    python -m venv .venv-bench
    .venv-bench/bin/pip install -e . -r benchmarks/requirements-pfilter.txt
    .venv-bench/bin/python benchmarks/filter_vs_pfilter.py

or simply: make bench"""

ROBOTS = ("r0", "r1", "r2", "r3", "r4")
REFERENCE = "r0"
AREA = (0.0, 8.0, 0.0, 9.0)  # xmin, xmax, ymin, ymax of the arena (m)
DT = 0.1  # s between updates
SPEED = 0.3  # m/s of every robot
SIGMA_ODOM = 0.02  # m per step, per robot and axis
PROCESS_NOISE = 0.03  # m/sqrt(s), relloc's OdometryMotion default
SIGMA_UWB = 0.15  # m
CLOUD_SPREAD = 0.3  # m, spread of the common starting cloud around the truth
WARMUP = 3


@dataclass(frozen=True)
class Step:
    """One simulated step: every robot's odometry displacement and the 10 measured ranges."""

    disp: FloatArray  # (N, 2), shared heading frame
    sigma: FloatArray  # (N,)
    ranges: FloatArray  # (K,)
    truth: FloatArray  # (N-1, 2) true relative positions after the step, for the sanity check


@dataclass(frozen=True)
class Scenario:
    layout: StateLayout
    pair_a: NDArray[np.intp]
    pair_b: NDArray[np.intp]
    start: FloatArray  # (N, 2) true positions at the start
    steps: list[Step]


def make_scenario(n_steps: int, rng: np.random.Generator) -> Scenario:
    """Five robots driving circles in an 8 m x 9 m arena, ranging between all pairs."""
    layout = StateLayout(ROBOTS, REFERENCE)
    n = len(ROBOTS)
    pair_a, pair_b = (np.asarray(ix, dtype=np.intp) for ix in np.triu_indices(n, k=1))
    centres = np.array([[2.0, 2.0], [6.0, 2.5], [4.0, 4.5], [2.5, 7.0], [6.0, 7.0]])
    radius = np.array([1.0, 1.2, 0.8, 1.1, 0.9])
    phase = rng.uniform(0.0, 2.0 * np.pi, n)
    omega = SPEED / radius * np.where(np.arange(n) % 2 == 0, 1.0, -1.0)

    def positions(k: int) -> FloatArray:
        angle = phase + omega * k * DT
        return centres + radius[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)

    steps = []
    for k in range(1, n_steps + 1):
        before, now = positions(k - 1), positions(k)
        disp = now - before + rng.normal(0.0, SIGMA_ODOM, (n, 2))
        true_ranges = np.linalg.norm(now[pair_a] - now[pair_b], axis=1)
        ranges = true_ranges + rng.normal(0.0, SIGMA_UWB, len(true_ranges))
        rel = np.delete(now - now[layout.index(REFERENCE)], layout.index(REFERENCE), axis=0)
        steps.append(Step(disp=disp, sigma=np.full(n, SIGMA_ODOM), ranges=ranges, truth=rel))
    return Scenario(layout, pair_a, pair_b, positions(0), steps)


def starting_cloud(scenario: Scenario, m: int, rng: np.random.Generator) -> FloatArray:
    """``m`` particles (``(m, 8)``) spread around the true relative formation."""
    ref = scenario.layout.index(REFERENCE)
    others = [scenario.layout.index(r) for r in scenario.layout.others]
    rel = (scenario.start[others] - scenario.start[ref]).reshape(-1)
    return rel + rng.normal(0.0, CLOUD_SPREAD, (m, rel.size))


# ----------------------------------------------------------------------------- relloc
class RellocRunner:
    """relloc's filter: predict + update + estimate + resample, every step."""

    name = "relloc"

    def __init__(
        self, scenario: Scenario, cloud: FloatArray, seed: int, published: bool = True
    ) -> None:
        self.scenario = scenario
        self.published = published
        self.pf = ParticleFilter(
            scenario.layout,
            cloud.shape[0],
            AREA,
            rng=np.random.default_rng(seed),
            motion=OdometryMotion(process_noise=PROCESS_NOISE),
            resample="every_step",
            reinject_fraction=0.01,
        )
        self.pf.particles = cloud.copy()
        k = len(scenario.pair_a)
        self.bias = np.zeros(k)
        self.sigma_uwb = np.full(k, SIGMA_UWB)

    def step(self, s: Step) -> FloatArray:
        self.pf.predict(s.disp, s.sigma, DT)
        ranges = RangeBatch(
            self.scenario.pair_a, self.scenario.pair_b, s.ranges, self.bias, self.sigma_uwb
        )
        self.pf.update([ranges])
        est = self.pf.estimate()
        if self.published and est.summary is not None:  # what a published estimate carries
            _ = (est.summary.shape, est.summary.distances)  # computed on first read
        self.pf.resample()
        return est.mean

    def phases(self, s: Step, clock: Callable[[], float]) -> dict[str, float]:
        """One :meth:`step`, each phase timed (``PHASES``), and the odometry noise of the
        predict drawn alone from the same compiled stream (into an array of its own): about
        the floor of any predict that draws those numbers."""
        batch = RangeBatch(
            self.scenario.pair_a, self.scenario.pair_b, s.ranges, self.bias, self.sigma_uwb
        )
        shipped = dataclasses.replace(
            batch,
            outlier_fraction=GROSS_FRACTION,
            nlos_fraction=NLOS_FRACTION,
            nlos_sigma=NLOS_SIGMA,
        )
        scratch = np.zeros(self.pf.particles.shape[0])
        t0 = clock()
        self.pf.predict(s.disp, s.sigma, DT)
        t1 = clock()
        self.pf.update([batch])
        t2 = clock()
        shipped.add_log_likelihood(self.pf.particles, self.pf.layout, scratch)  # nothing kept
        t2_nlos = clock()
        est = self.pf.estimate()
        t3 = clock()
        assert est.summary is not None
        _ = (est.summary.shape, est.summary.distances)
        t4 = clock()
        self.pf.resample()
        t5 = clock()
        m, k = self.pf.particles.shape[0], self.pf.layout.n_others
        t6 = clock()
        standard_normal(0, m * (k + 1) * 2)  # the predict's draws: k own pairs, 1 shared
        t7 = clock()
        times = (t1 - t0, t2 - t1, t3 - t2_nlos, t4 - t3, t5 - t4, t7 - t6, t2_nlos - t2)
        return dict(zip(PHASES, times, strict=True))


PHASES = (
    "predict",
    "likelihood (update)",
    "moments and modes",
    "shape and distances",
    "resample",
    "noise draws alone",
    "likelihood, NLOS-aware",
)
"""What :meth:`RellocRunner.phases` times: the update's phases; the predict's noise drawn alone
(about its floor); and the likelihood of the same ranges under the NLOS-aware model the shipped
config gives calibrated ranges (the benchmark's update uses the symmetric one), computed as
the update computes it but kept nowhere."""


def phase_table(phases: dict[str, dict[str, float]], context: str) -> str:
    """The Markdown table of ``--phases`` (median ms per step, per M)."""
    ms = list(phases)
    lines = [
        f"Written by `benchmarks/filter_vs_pfilter.py --phases --readme` ({context}):",
        "",
        "| phase | " + " | ".join(f"M = {int(m):,}".replace(",", " ") for m in ms) + " |",
        "|---|" + "---:|" * len(ms),
    ]
    for name in PHASES:
        lines.append(
            f"| {name} | " + " | ".join(f"{phases[m][name] * 1e3:.3f} ms" for m in ms) + " |"
        )
    return "\n".join(lines)


# ----------------------------------------------------------------------------- pfilter
class PfilterRunner:
    """The research configuration on ``pfilter.ParticleFilter`` (functions vectorised, as documented)."""

    name = "pfilter"

    def __init__(
        self, pfilter: Any, scenario: Scenario, cloud: FloatArray, seed: int, resample: str
    ) -> None:
        np.random.seed(seed)  # pfilter draws from the legacy global state
        layout = scenario.layout
        n_others = len(layout.others)
        ref = layout.index(REFERENCE)
        others = np.array([layout.index(r) for r in layout.others], dtype=np.intp)
        mask = np.array([r != REFERENCE for r in layout.robots])
        half_extent = np.array([AREA[1] - AREA[0], AREA[3] - AREA[2]])
        pair_a, pair_b = scenario.pair_a, scenario.pair_b
        n_robots = len(layout.robots)
        # Per-axis std of a relative position: own odometry, random walk, reference odometry.
        sigma = np.sqrt(2.0 * SIGMA_ODOM**2 + PROCESS_NOISE**2 * DT)
        sigmas = np.full(2 * n_others, sigma)

        def prior_fn(n: int) -> FloatArray:
            u = np.random.uniform(-1.0, 1.0, size=(n, n_others, 2)) * half_extent
            return u.reshape(n, 2 * n_others)

        def dynamics_fn(x: FloatArray, odom: FloatArray, **_: Any) -> FloatArray:
            return x + (odom[others] - odom[ref]).reshape(-1)

        def noise_fn(x: FloatArray, **_: Any) -> FloatArray:
            return pfilter.gaussian_noise(x, sigmas=sigmas)

        def observe_fn(x: FloatArray, **_: Any) -> FloatArray:
            pos = np.zeros((x.shape[0], n_robots, 2))
            pos[:, mask, :] = x.reshape(x.shape[0], n_others, 2)
            diff = pos[:, pair_a, :] - pos[:, pair_b, :]
            return np.sqrt(np.sum(diff * diff, axis=2))

        def weight_fn(hyp: FloatArray, real: FloatArray, **_: Any) -> FloatArray:
            return pfilter.squared_error(hyp, real, sigma=SIGMA_UWB)

        resample_fn: Callable[[FloatArray], Any] | None = None
        if resample == "systematic":
            resample_fn = pfilter.systematic_resample
        self.pf = pfilter.ParticleFilter(
            prior_fn=prior_fn,
            observe_fn=observe_fn,
            resample_fn=resample_fn,  # None: pfilter's default (as in its README)
            n_particles=cloud.shape[0],
            dynamics_fn=dynamics_fn,
            noise_fn=noise_fn,
            weight_fn=weight_fn,
            resample_proportion=0.01,
            column_names=[f"{r}_{ax}" for r in layout.others for ax in "xy"],
        )
        self.pf.particles = cloud.copy()

    def step(self, s: Step) -> FloatArray:
        self.pf.update(s.ranges, odom=s.disp)
        return np.asarray(self.pf.mean_state).reshape(-1, 2)


# ----------------------------------------------------------------------------- timing
Runner = RellocRunner | PfilterRunner


def time_pair(
    runners: Sequence[Runner],
    steps: Sequence[Step],
    reps: Sequence[int],
    clock: Callable[[], float] = time.perf_counter,
) -> tuple[list[list[float]], list[list[float]]]:
    """Interleave the runners over ``steps``; runner ``i`` is timed ``reps[i]`` times.

    On step ``k`` the runners go in turn, the first one alternating with ``k``. A runner that
    has used its repetitions sits out the remaining steps. Returns the update times and, as a
    check that both filters track the team, the estimate's RMS position error of every step.
    """
    times: list[list[float]] = [[] for _ in runners]
    errors: list[list[float]] = [[] for _ in runners]
    for runner in runners:
        for s in steps[:WARMUP]:
            runner.step(s)
    gc.collect()
    for k, s in enumerate(steps[WARMUP : WARMUP + max(reps)]):
        order = list(range(len(runners)))
        if k % 2:
            order.reverse()
        for i in order:
            if k >= reps[i]:
                continue
            t0 = clock()
            mean = runners[i].step(s)
            times[i].append(clock() - t0)
            errors[i].append(float(np.sqrt(np.mean(np.sum((mean - s.truth) ** 2, axis=1)))))
    return times, errors


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument(
        "--particles", type=int, nargs="+", default=[400, 4000, 40000], help="particle counts M"
    )
    parser.add_argument(
        "--reps", type=int, default=40, help="timed updates per implementation and M"
    )
    parser.add_argument(
        "--reps-large",
        type=int,
        default=20,
        help="timed pfilter updates at M >= 40000 with its default (quadratic) resampler",
    )
    parser.add_argument(
        "--pfilter-resample",
        choices=("default", "systematic"),
        default="default",
        help="pfilter's resample_fn: its default (as documented) or its systematic_resample",
    )
    parser.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="wall: time.perf_counter (default); cpu: time.process_time, this process's CPU "
        "time over all its threads, steadier on a shared machine",
    )
    parser.add_argument(
        "--estimate",
        choices=("published", "moments"),
        default="published",
        help="relloc's estimate per step: all a published estimate carries (default), or only "
        "the dominant mode's moments (a step nobody publishes)",
    )
    parser.add_argument(
        "--malloc",
        choices=("tuned", "default"),
        default="tuned",
        help="tuned: glibc keeps freed memory mapped, as the relloc command does (relloc.malloc; "
        "process-wide, so for both implementations); default: glibc's own settings",
    )
    parser.add_argument(
        "--readme",
        type=Path,
        help="write the figures into this Markdown file, between its "
        f"{README_BEGIN} and {README_END} markers",
    )
    parser.add_argument(
        "--phases",
        action="store_true",
        help="also time relloc's update phase by phase (and the predict's noise draws alone)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="write the medians and speed-ups to this file")
    args = parser.parse_args(argv)

    if args.malloc == "tuned":
        tune_malloc()
    try:
        import pfilter  # optional: lives in the benchmark environment only
    except ImportError:
        print(SETUP_HINT, file=sys.stderr)
        return 2
    # pfilter's weight entropy takes log(0) for particles of zero weight (those re-drawn from the
    # prior far from the ranges); harmless, and not ours to fix.
    warnings.filterwarnings("ignore", category=RuntimeWarning, module="pfilter")

    version = getattr(pfilter, "__version__", None) or dist_version("pfilter")
    print(
        f"relloc vs pfilter {version}: 5 robots, 8-dim state, 10 ranges per update, resampling every step; "
        f"numpy {np.__version__}, Python {platform.python_version()}, pfilter resample_fn: {args.pfilter_resample}, clock: {args.clock}"
    )
    n_steps = WARMUP + args.reps
    results: dict[str, dict[str, float]] = {}
    reps_used: dict[str, tuple[int, int]] = {}
    header = f"{'M':>7}  {'relloc / update':>16}  {'pfilter / update':>17}  {'speed-up':>9}  reps (relloc, pfilter)  median RMS error (relloc, pfilter)"
    print(header)
    for m in args.particles:
        rng = np.random.default_rng(args.seed)
        scenario = make_scenario(n_steps, rng)
        cloud = starting_cloud(scenario, m, rng)
        runners: list[Runner] = [
            RellocRunner(scenario, cloud, args.seed, published=args.estimate == "published"),
            PfilterRunner(pfilter, scenario, cloud, args.seed, args.pfilter_resample),
        ]
        pf_reps = args.reps
        if m >= 40000 and args.pfilter_resample == "default":
            pf_reps = min(args.reps, args.reps_large)
        clock = time.process_time if args.clock == "cpu" else time.perf_counter
        times, errors = time_pair(runners, scenario.steps, [args.reps, pf_reps], clock)
        relloc_s = statistics.median(times[0])
        pfilter_s = statistics.median(times[1])
        speedup = pfilter_s / relloc_s
        results[str(m)] = {"relloc_s": relloc_s, "pfilter_s": pfilter_s, "speedup": speedup}
        reps_used[str(m)] = (len(times[0]), len(times[1]))
        print(
            f"{m:>7}  {relloc_s * 1e3:>13.3f} ms  {pfilter_s * 1e3:>14.3f} ms  {speedup:>8.1f}x  "
            f"({len(times[0])}, {len(times[1])})  "
            f"{statistics.median(errors[0]):.3f} m, {statistics.median(errors[1]):.3f} m"
        )
    phases: dict[str, dict[str, float]] = {}
    if args.phases:
        clock = time.process_time if args.clock == "cpu" else time.perf_counter
        for m in args.particles:
            rng = np.random.default_rng(args.seed)
            scenario = make_scenario(n_steps, rng)
            runner = RellocRunner(scenario, starting_cloud(scenario, m, rng), args.seed)
            for s in scenario.steps[:WARMUP]:
                runner.step(s)
            timed = [runner.phases(s, clock) for s in scenario.steps[WARMUP:]]
            phases[str(m)] = {name: statistics.median(t[name] for t in timed) for name in PHASES}
            print(
                f"{m:>7}  "
                + ", ".join(f"{name} {v * 1e3:.3f} ms" for name, v in phases[str(m)].items())
            )
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps({**results, **({"phases": phases} if phases else {})}, indent=2) + "\n"
        )
        print(f"wrote {args.json}")
    if args.readme is not None:
        context = (
            f"pfilter {version} (resample_fn: {args.pfilter_resample}), relloc's estimate: {args.estimate}, "
            f"clock: {args.clock}, malloc: {args.malloc}; numpy {np.__version__}, Python {platform.python_version()}, "
            f"{os.cpu_count()} CPUs"
        )
        write_readme(args.readme, results, reps_used, context)
        if phases:
            write_between(args.readme, "filter_phases", phase_table(phases, context))
        print(f"wrote the figures into {args.readme}")
    return 0


README_BEGIN, README_END = markers("filter_vs_pfilter")


def figures_table(
    results: dict[str, dict[str, float]], reps: dict[str, tuple[int, int]], context: str
) -> str:
    """The Markdown figures of one run (what ``--readme`` writes)."""
    lines = [
        f"Written by `benchmarks/filter_vs_pfilter.py --readme` ({context}):",
        "",
        "| M | relloc / update | pfilter / update | speed-up | reps (relloc, pfilter) |",
        "|---:|---:|---:|---:|---:|",
    ]
    for m, r in results.items():
        lines.append(
            f"| {int(m):,} | {r['relloc_s'] * 1e3:.3f} ms | {r['pfilter_s'] * 1e3:.2f} ms | ".replace(
                ",", " "
            )
            + f"{r['speedup']:.1f}x | {reps[m][0]}, {reps[m][1]} |"
        )
    return "\n".join(lines)


def write_readme(
    path: Path, results: dict[str, dict[str, float]], reps: dict[str, tuple[int, int]], context: str
) -> None:
    """Replace the text between the markers of ``path`` with this run's figures."""
    write_between(path, "filter_vs_pfilter", figures_table(results, reps, context))


if __name__ == "__main__":
    sys.exit(main())
