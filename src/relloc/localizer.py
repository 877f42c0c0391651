"""The localizer: the one holder of filter state. Events in, estimates out.

Sensors are asynchronous: each robot's odometry, each UWB pair and each camera arrive at their
own rates and lags. The localizer

* validates every event (non-finite values, negative ranges, unknown robots, time going
  backwards): a bad event is **rejected and counted** in :attr:`Localizer.stats` (and logged),
  never allowed to crash the engine or to corrupt the estimate;
* keeps each robot's odometry in an :class:`~relloc.odometry.OdometryTrack` (shared heading
  frame), so that it can predict to any instant;
* gathers the measurements stamped within one cell of a fixed ``update_period`` grid into one
  batch, predicts with every robot's odometry up to the batch time (its newest stamp), and
  fuses the batch in one update (the stacked measurement vector of the paper). A grid, not a
  window opened by the first measurement: a pair ranging at the update rate with some jitter
  then gives one range per batch, not now one, now two;
* emits an :class:`Estimate` (each robot's position relative to the reference, with covariance)
  at ``estimate_period``.

:class:`ParticleFilterLocalizer` and :class:`MultilaterationLocalizer` share all of this and
differ only in ``_step``, the fusion of one batch.
"""

from __future__ import annotations

import logging
import math
import numbers
import statistics
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.events import (
    DetectionEvent,
    Event,
    GroundTruthEvent,
    OdometryEvent,
    RangeEvent,
    RelativeObservation,
    pair_key,
)
from relloc.filter import multilateration
from relloc.filter.gaussian_sum import CalibrationLayout, CalibrationNoise, GaussianSumFilter
from relloc.filter.models import OdometryMotion, RangeBatch, RelativePositionBatch
from relloc.filter.pf import ParticleFilter
from relloc.filter.resampling import mixture_moments, normalize, systematic_resample
from relloc.filter.state import StateLayout
from relloc.odometry import OdometryTrack

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
Measurement = RangeEvent | RelativeObservation

_TIME_TOLERANCE = 1e-9
_JUMP_VOTES = 3
"""Events in a row that must agree on a time far ahead before the clock follows them."""

_YAW_LOG = 200_000
"""Odometry yaws kept per robot for evaluation (heading-estimate mode): 5.5 h at 10 Hz."""


def _finite(x: object) -> bool:
    """A finite real number (not a bool, a string or an array): what every event field must be."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x)


class Localizer:
    """Validation, odometry tracks and measurement batching common to every method."""

    method = "base"

    def __init__(self, config: TeamConfig) -> None:
        self.config = config
        self.layout = StateLayout(config.robot_names, config.reference)
        fc = config.filter
        self.update_period = fc.update_period
        self.estimate_period = fc.estimate_period
        self.heading_estimated = fc.heading_mode == "estimate"
        self.scale_estimated = fc.odom_scale_mode == "online"
        # In an estimate/online mode the config's value of that quantity is not read: odometry
        # stays in the robot's own frame (heading) or unscaled (scale), the filter applies them.
        self.tracks = {
            r.name: OdometryTrack(
                0.0 if self.heading_estimated else r.heading_offset,
                1.0 if self.scale_estimated else r.odom_scale,
                r.odom_mode,
                max_extrapolation=fc.max_odom_extrapolation,
            )
            for r in config.robots
        }
        self.first_odometry: dict[str, tuple[float, float]] = {}
        """Per robot, ``(t, yaw)`` of its first odometry sample (in its track's frame)."""
        self.stats: Counter[str] = Counter()
        self._pending: list[Measurement] = []
        self._batch_start = math.nan
        self._closed_until = -math.inf  # measurements older than this come too late
        self._last_range: dict[tuple[str, str], float] = {}
        self._last_emit = -math.inf
        self._clock = -math.inf  # newest accepted stamp
        self._jump_candidate = math.nan  # stamp of the last event rejected as a time jump
        self._jump_votes = 0  # consecutive rejected events that agree with it

    # ---------------------------------------------------------------- public API
    def process(self, event: Event) -> list[Estimate]:
        """Consume one event; returns the estimates that became due (often none)."""
        reason = self._rejection(event)
        if reason is not None:
            self._reject(reason, event)
            return []
        if isinstance(event, OdometryEvent | RangeEvent | RelativeObservation):
            self._clock = max(self._clock, event.t)
        if isinstance(event, OdometryEvent):
            track = self.tracks[event.robot]
            first = track.empty
            track.add(event)
            if first:
                self.first_odometry[event.robot] = (event.t, track.pose_at(event.t)[2])
            self.stats["odometry"] += 1
            return self._advance(event.t)
        if isinstance(event, RangeEvent | RelativeObservation):
            out: list[Estimate] = []
            if self._pending and self._cell(event.t) > self._cell(self._batch_start):
                out += self._run_batch()
            if not self._pending:
                self._batch_start = event.t
            self._pending.append(event)
            self.stats["range" if isinstance(event, RangeEvent) else "relative"] += 1
            return out
        self.stats["ignored_" + type(event).__name__] += 1
        return []

    def flush(self) -> list[Estimate]:
        """Fuse what is still pending (end of a recording)."""
        return self._run_batch() if self._pending else []

    # ---------------------------------------------------------------- validation
    def _rejection(self, event: Event) -> str | None:
        if isinstance(event, GroundTruthEvent | DetectionEvent):
            return None
        if not isinstance(event, OdometryEvent | RangeEvent | RelativeObservation):
            return "unknown_event_type"
        if not _finite(event.t):
            return "invalid_time"
        if self._time_jump(event.t):
            return "time_jump"
        names = self.layout.robots
        if isinstance(event, OdometryEvent):
            if event.robot not in names:
                return "unknown_robot"
            if not all(map(_finite, (event.x, event.y, event.yaw, event.v, event.w))):
                return "invalid_odometry"
            if event.t <= self.tracks[event.robot].last_time + _TIME_TOLERANCE:
                return "out_of_order_odometry"
            return None
        if isinstance(event, RangeEvent):
            if event.robot_a not in names or event.robot_b not in names:
                return "unknown_robot"
            if event.robot_a == event.robot_b:
                return "self_range"
            d = event.distance
            if not _finite(d) or d <= 0.0 or d > self.config.filter.max_range:
                return "invalid_range"
            if event.t < self._closed_until:
                return "late_measurement"
            if self.layout.bias_pairs and not event.corrected and self._event_node_pair(event) not in self.layout.bias_pairs:
                return "unknown_node_pair"  # online biases: the state has a column per configured pair only
            key = (event.robot_a, event.robot_b) if event.robot_a < event.robot_b else (event.robot_b, event.robot_a)
            if self._last_range.get(key) == d:
                # Equal to the pair's previous range: a driver re-publishing a stale sample, or a
                # new one that the 1 cm resolution made equal (in the TIERS bags 10-17 % of
                # ranges, at the normal cadence). Dropped either way: fusing them too, with the
                # likelihood treating each batch as independent evidence, put the shortbag PF
                # at 0.117 m instead of 0.069 (seed 0; 0.106 vs 0.091 over seeds 0-4).
                return "repeated_range"
            self._last_range[key] = d
            return None
        # a RelativeObservation
        if event.observer not in names or event.target not in names:
            return "unknown_robot"
        if event.observer == event.target:
            return "self_observation"
        if not all(map(_finite, (event.dx, event.dy, event.sigma))) or event.sigma <= 0:
            return "invalid_relative_observation"
        if event.t < self._closed_until:
            return "late_measurement"
        return None

    def _cell(self, t: float) -> int:
        """Index of the batching grid cell that holds time ``t``."""
        return math.floor(t / self.update_period)

    def _time_jump(self, t: float) -> bool:
        """Whether ``t`` jumps ahead of the clock by more than ``max_time_jump`` without
        ``_JUMP_VOTES`` events in a row agreeing on the new time (see
        :class:`relloc.config.FilterConfig`)."""
        limit = self.config.filter.max_time_jump
        if self._clock == -math.inf or t <= self._clock + limit:
            return False  # the first event sets the clock
        agrees = abs(t - self._jump_candidate) <= limit
        self._jump_votes = self._jump_votes + 1 if agrees else 1
        self._jump_candidate = t
        if self._jump_votes < _JUMP_VOTES:
            return True
        self._jump_votes, self._jump_candidate = 0, math.nan
        return False

    def _reject(self, reason: str, event: Event) -> None:
        self.stats["rejected_" + reason] += 1
        n = self.stats["rejected_" + reason]
        if n == 1 or n % 1000 == 0:
            log.warning("rejected %s (%s, %d so far): %r", type(event).__name__, reason, n, event)

    @property
    def rejected(self) -> dict[str, int]:
        return {k.removeprefix("rejected_"): v for k, v in self.stats.items() if k.startswith("rejected_")}

    # ---------------------------------------------------------------- batching
    def _advance(self, now: float) -> list[Estimate]:
        """Odometry moved the clock: fuse a batch that is complete by now."""
        if self._pending and now >= (self._cell(self._batch_start) + 2) * self.update_period:
            return self._run_batch()
        return []

    def _run_batch(self) -> list[Estimate]:
        batch, self._pending = self._pending, []
        t = max(m.t for m in batch)
        # The filter is now at t: a measurement stamped before it can no longer be fused.
        self._closed_until = max(self._closed_until, t)
        est = self._step(t, batch)
        if est is None:
            return []
        # A batch is stamped with its newest measurement, so batch times jitter within a window:
        # half a window of tolerance keeps one estimate per estimate_period.
        if est.t - self._last_emit >= self.estimate_period - 0.5 * self.update_period:
            self._last_emit = est.t
            return [est]
        return []

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        raise NotImplementedError

    # ---------------------------------------------------------------- helpers for subclasses
    def _node_pair(self, robot_a: str, robot_b: str) -> str:
        """Key of the UWB transceiver pair between two robots (robot names if no node ids)."""
        a = self.config.robot(robot_a).uwb_node or robot_a
        b = self.config.robot(robot_b).uwb_node or robot_b
        return pair_key(a, b)

    def _event_node_pair(self, event: RangeEvent) -> str:
        """Key of the transceiver pair of a range (:meth:`TeamConfig.range_nodes`)."""
        return pair_key(*self.config.range_nodes(event))

    def _pair_sigma(self, node_pair: str, base: float) -> float:
        """Noise of a raw range of ``node_pair`` (after its scale is divided out): the pair's
        calibrated sigma, else ``base``, over its scale; an uncalibrated pair's ``base``
        widened by ``uwb.default_bias_sigma`` (its bias is only the default)."""
        uwb = self.config.uwb
        cal = uwb.pairs.get(node_pair)
        if cal is None:
            return math.hypot(base, uwb.default_bias_sigma)
        return (cal.sigma if cal.sigma is not None else base) / cal.scale

    def _pair_ranges(
        self, batch: list[Measurement], online_bias: bool = False
    ) -> tuple[list[tuple[int, int]], FloatArray, FloatArray, FloatArray, list[str]]:
        """Per robot pair in the batch: median range, bias, sigma and node-pair key (or ``""``
        where the range was corrected upstream and carries no bias).

        With ``online_bias`` the bias is left to the particles (returned as 0) and the sigma
        is the plain range noise. A calibrated pair's scale (``measured = scale * true +
        bias``) is applied here, to range, bias and sigma alike, so every consumer sees
        ``range = true + bias + noise``.

        Several ranges of one pair in a batch are not independent evidence (their errors are
        strongly correlated over a tenth of a second): the median stands for them.
        """
        groups: dict[tuple[int, int], list[RangeEvent]] = {}
        for m in batch:
            if isinstance(m, RangeEvent):
                a, b = self.layout.index(m.robot_a), self.layout.index(m.robot_b)
                groups.setdefault((min(a, b), max(a, b)), []).append(m)
        pairs, dist, bias, sigma, keys = [], [], [], [], []
        fc, uwb = self.config.filter, self.config.uwb
        for key, events in groups.items():
            nodes = self.config.range_nodes(events[0])
            node_pair = pair_key(*nodes)
            d = float(statistics.median(ev.distance for ev in events))  # a few values: no NumPy
            if all(ev.corrected for ev in events):
                b, s, node_pair = 0.0, fc.sigma_uwb, ""
            elif online_bias:
                b, s = 0.0, fc.sigma_uwb
            else:
                b, scale, _ = uwb.calibration(*nodes)
                d, b, s = d / scale, b / scale, self._pair_sigma(node_pair, fc.sigma_uwb)
            pairs.append(key)
            dist.append(d)
            bias.append(b)
            sigma.append(s)
            keys.append(node_pair)
        return pairs, np.array(dist), np.array(bias), np.array(sigma), keys


@dataclass(frozen=True)
class StackedMeasurement:
    """Everything that arrived in one batch, fused as one measurement (the paper's stacked
    measurement vector): the log-likelihoods of the parts add up."""

    parts: tuple[RangeBatch | RelativePositionBatch, ...]

    def log_likelihood(self, positions: FloatArray, particles: FloatArray) -> FloatArray:
        total = self.parts[0].log_likelihood(positions, particles)
        for part in self.parts[1:]:
            total = total + part.log_likelihood(positions, particles)
        return total

    def kalman_update(self, pf: ParticleFilter) -> None:
        """Update the particles' online range-bias beliefs (no-op without online biases)."""
        for part in self.parts:
            if isinstance(part, RangeBatch) and part.bias_columns is not None:
                part.kalman_update(pf.positions(), pf.particles)


class ParticleFilterLocalizer(Localizer):
    """Odometry + UWB ranges (+ relative observations from detections) in a particle filter."""

    method = "pf"

    def __init__(self, config: TeamConfig, *, seed: int = 0, method: str = "pf") -> None:
        super().__init__(config)
        self.method = method
        fc = config.filter
        self.rng = np.random.default_rng(seed)
        self.online_bias = fc.bias_mode == "online"
        extra: list[float] = []
        if self.online_bias:
            names = config.robot_names
            node_pairs = sorted({self._node_pair(a, b) for i, a in enumerate(names) for b in names[i + 1 :]})
            self.layout = StateLayout(config.robot_names, config.reference, tuple(node_pairs))
            for pair in node_pairs:
                cal = config.uwb.pairs.get(pair)
                if cal is not None:
                    extra += [cal.bias, fc.bias_prior_sigma**2]
                else:
                    extra += [config.uwb.default_bias, fc.bias_prior_sigma_uncalibrated**2]
        self.gsf: GaussianSumFilter | None = None
        self.odometry_yaws: dict[str, deque[tuple[float, float]]] = {}
        """Heading-estimate mode: each robot's odometry yaw at every estimate time (for
        evaluating the published headings; the filter does not use it). Bounded, for live runs."""
        n_start = fc.particles
        if self.heading_estimated or self.scale_estimated:
            # Self-calibration: a Gaussian-sum filter; the sampled filter below only serves its
            # annealed start (relloc.filter.gaussian_sum explains why).
            n_start = max(fc.selfcal_init_particles, fc.selfcal_particles)
            self.gsf = self._build_gaussian_sum(np.array(extra))
        self.pf = ParticleFilter(
            self.layout,
            n_start,
            config.area,
            rng=self.rng,
            motion=OdometryMotion(process_noise=fc.process_noise),
            resample=fc.resample,
            ess_threshold=fc.ess_threshold,
            reinject_fraction=fc.reinject_fraction,
            extra_prior=np.array(extra),
            rotation_kernel=fc.rotation_kernel,
            rotation_kernel_max_spread=fc.rotation_kernel_max_spread,
        )
        # The self-calibrating filter has its own (symmetric) range update; its annealed start
        # uses the same model. With online biases an unknown bias and a one-sided NLOS excess
        # are confounded (a positive offset reads as either), and the inlier-weighted Kalman
        # update of the bias came out about 1 cm low in simulation: those modes keep the
        # symmetric model.
        self.range_model = fc.range_model if self.gsf is None and not self.online_bias else "symmetric"
        self.initialized = False
        self.t = math.nan
        self._anchor: dict[str, tuple[float, float, float]] = {}
        self._init_batch: list[Measurement] = []
        self.last_estimate: Estimate | None = None

    def _build_gaussian_sum(self, bias_prior: FloatArray) -> GaussianSumFilter:
        fc = self.config.filter
        layout = CalibrationLayout(
            self.layout.robots,
            self.layout.reference,
            heading=self.heading_estimated,
            scale=self.scale_estimated,
            bias_pairs=self.layout.bias_pairs,
        )
        prior = None
        if len(layout.bias_pairs):
            prior = (bias_prior[0::2], bias_prior[1::2])
        heading_prior: dict[str, tuple[float, float]] = {}
        if self.heading_estimated and fc.heading_prior_sigma_deg > 0.0:
            ref = self.config.robot(layout.reference).heading_offset
            for robot in layout.others:
                angle = math.remainder(self.config.robot(robot).heading_offset - ref, math.tau)
                heading_prior[robot] = (angle, math.radians(fc.heading_prior_sigma_deg))
        noise = CalibrationNoise(
            heading_walk=fc.heading_walk,
            reference_heading_walk=fc.reference_heading_walk,
            scale_walk=fc.scale_walk,
            bias_walk=fc.bias_walk,
            scale_prior_sigma=fc.scale_prior_sigma,
        )
        return GaussianSumFilter(
            layout,
            fc.selfcal_particles,
            self.config.area,
            rng=self.rng,
            noise=noise,
            bias_prior=prior,
            position_sigma=fc.selfcal_position_sigma,
            process_noise=fc.process_noise,
            ess_threshold=fc.ess_threshold,
            reinject_fraction=fc.reinject_fraction,
            heading_prior=heading_prior,
        )

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        if not self.initialized:
            self._init_batch += batch
            first = min(m.t for m in self._init_batch)
            if t - first < self.config.filter.init_window:
                return None
            return self._initialize(t)
        if self.gsf is not None:
            return self._step_gaussian_sum(t, batch)
        self._predict(t)
        model = self._model(batch)
        if model is not None:
            ll = self.pf.update(model.log_likelihood)
            if not np.any(np.isfinite(ll)):
                self.stats["update_no_support"] += 1
            model.kalman_update(self.pf)
        est = self._estimate(t)
        if self.pf.maybe_resample():
            self.stats["resampled"] += 1
        self.stats["rotation_kernel"] = self.pf.rotation_kernel_count
        return est

    def _initialize(self, t: float) -> Estimate | None:
        batch, self._init_batch = self._init_batch, []
        fc = self.config.filter
        # Heading-estimate mode has no compass frame for the detection vectors: ranges only.
        vectors = [] if self.heading_estimated else [m for m in batch if isinstance(m, RelativeObservation)]
        ranges = [m for m in batch if not isinstance(m, RelativeObservation)]
        # Ranges are invariant under rotations and reflections about the reference, vectors are
        # not: anneal on the ranges, spread over those symmetries (exact), then weight by the
        # vectors. Annealing on both and skipping the spread left the mirror image about the
        # line of a single vector to chance (a sharp range likelihood picked one side).
        spread = fc.spread_rotations and bool(ranges)
        anneal_on = ranges if spread else ranges + vectors
        model = self._model(anneal_on)
        guide = self._model(anneal_on, outliers=False)
        if model is None or guide is None:
            return None
        stages = self.pf.initialize_annealed(model.log_likelihood, guide.log_likelihood, mcmc_steps=fc.mcmc_steps)
        self.stats["anneal_stages"] = stages
        if spread:
            self.pf.spread_symmetries()
            vector_model = self._model(vectors) if vectors else None
            if vector_model is not None:
                self.pf.update(vector_model.log_likelihood)
                if self.pf.maybe_resample():
                    self.stats["resampled"] += 1
        self.initialized = True
        self.t = t
        self._anchor = {r: self._odometry_pose(r, t) for r in self.layout.robots}
        if self.gsf is not None:
            return self._start_gaussian_sum(t)
        return self._estimate(t)

    def _odometry_pose(self, robot: str, t: float) -> tuple[float, float, float]:
        track = self.tracks[robot]
        if track.empty:
            return (math.nan, math.nan, math.nan)
        x, y, yaw, _ = track.pose_at(t)
        return (x, y, yaw)

    def _predict(self, t: float) -> None:
        fc = self.config.filter
        n = len(self.layout.robots)
        disp = np.zeros((n, 2))
        sigma = np.zeros(n)
        for i, robot in enumerate(self.layout.robots):
            now = self._odometry_pose(robot, t)
            before = self._anchor.get(robot, (math.nan,) * 3)
            if math.isnan(now[0]):
                continue
            if math.isnan(before[0]):
                before = now  # odometry started since the last step: no known motion yet
            disp[i] = (now[0] - before[0], now[1] - before[1])
            dist = math.hypot(*disp[i])
            turn = abs(math.remainder(now[2] - before[2], math.tau))
            sigma[i] = fc.odom_noise_per_m * dist + fc.odom_noise_per_rad * turn
            self._anchor[robot] = now
        dt = max(t - self.t, 0.0)
        if self.gsf is not None:
            self.gsf.predict(disp, sigma, dt)
            self.t = t
            return
        self.pf.predict(disp, sigma, dt, fc.rotation_noise)
        if self.online_bias and dt > 0.0:
            self.pf.particles[:, self.layout.dim + 1 :: 2] += fc.bias_walk**2 * dt  # variances
        self.t = t

    # ---------------------------------------------------------------- self-calibration
    def _start_gaussian_sum(self, t: float) -> Estimate:
        """Hand the annealed particles to the Gaussian-sum filter (one Gaussian per particle)."""
        assert self.gsf is not None
        gsf, particles = self.gsf, self.pf.particles
        if particles.shape[0] != gsf.n or np.ptp(self.pf.logw) > 0.0:  # (the vectors' weights)
            idx = systematic_resample(normalize(self.pf.logw), self.rng, gsf.n)
            particles = particles[idx]
        gsf.initialize(particles[:, : self.layout.dim])
        # the sampled filter is no longer needed: keep a one-particle stub, free the memory
        self.pf.particles = self.pf.particles[:1]
        return self._estimate_gaussian_sum(t)

    def _step_gaussian_sum(self, t: float, batch: list[Measurement]) -> Estimate:
        assert self.gsf is not None
        gsf, fc = self.gsf, self.config.filter
        self._predict(t)
        pairs, dist, bias, sigma, keys = self._pair_ranges(batch, self.online_bias)
        for (a, b), z, bb, s, key in zip(pairs, dist, bias, sigma, keys, strict=True):
            column = gsf.layout.bias_column(key) if self.online_bias and key else -1
            gsf.update_range(int(a), int(b), float(z), float(s), float(bb), column, fc.outlier_fraction, fc.max_range)
        for m in batch:
            if isinstance(m, RelativeObservation):
                if self.heading_estimated:
                    # its vector is in the compass frame, which this mode does not have
                    self.stats["ignored_relative_heading_estimate"] += 1
                    continue
                gsf.update_vector(
                    self.layout.index(m.observer), self.layout.index(m.target), np.array([m.dx, m.dy]), m.sigma
                )
        if self.heading_estimated:
            self.stats["scale_priors_applied"] += gsf.apply_magnitude_priors(np.ones(gsf.layout.n_others))
        if not gsf.normalize():
            self.stats["update_no_support"] += 1
        gsf.symmetrize()
        est = self._estimate_gaussian_sum(t)
        if gsf.maybe_resample():
            self.stats["resampled"] += 1
        return est

    def _estimate_gaussian_sum(self, t: float) -> Estimate:
        assert self.gsf is not None
        gsf = self.gsf
        positions, covs = self._positions(*gsf.position_moments())
        headings, biases, scales = {}, {}, {}
        if self.heading_estimated:
            for robot in self.layout.robots:  # the reference's: the drift of its own heading
                headings[robot] = gsf.heading(robot)
                if not self.tracks[robot].empty:
                    log_ = self.odometry_yaws.setdefault(robot, deque(maxlen=_YAW_LOG))
                    log_.append((t, self.tracks[robot].pose_at(t)[2]))
        for pair in gsf.layout.bias_pairs:
            biases[pair] = gsf.bias(pair)
        if self.scale_estimated:
            for robot in self.layout.robots:
                scales[robot] = gsf.scale(robot)
        est = Estimate(
            t, self.method, self.layout.reference, positions, covs, gsf.ess(), headings, biases, scales
        )
        self.last_estimate = est
        return est

    def _model(self, batch: list[Measurement], outliers: bool = True) -> StackedMeasurement | None:
        """The stacked measurement of a batch; ``outliers=False`` drops the robust floor (the
        plain Gaussian that guides the annealed start)."""
        fc = self.config.filter
        pairs, dist, bias, sigma, keys = self._pair_ranges(batch, self.online_bias)
        parts: list[RangeBatch | RelativePositionBatch] = []
        if pairs:
            idx = np.array(pairs, dtype=np.intp)
            columns = None
            if self.online_bias:
                columns = np.array([self.layout.bias_columns(k)[0] if k else -1 for k in keys], dtype=np.intp)
            # Raw ranges get the NLOS-aware model (fitted to raw UWB errors); ranges corrected
            # upstream by a learned model (key "") keep the symmetric one: the correction has
            # already predicted the skewed part of their error.
            raw = np.array([bool(k) for k in keys]) if self.range_model == "nlos" else np.zeros(len(keys), bool)
            for sel, nlos in ((raw, True), (~raw, False)):
                if not np.any(sel):
                    continue
                s = self._los_sigmas(keys)[sel] if nlos else sigma[sel]
                eps = (fc.gross_fraction if nlos else fc.outlier_fraction) if outliers else 0.0
                parts.append(
                    RangeBatch(
                        idx[sel, 0], idx[sel, 1], dist[sel], bias[sel], s, eps, fc.max_range,
                        None if columns is None else columns[sel],
                        nlos_fraction=fc.nlos_fraction if nlos and outliers else 0.0,
                        nlos_sigma=fc.nlos_sigma,
                    )
                )
        vectors = [m for m in batch if isinstance(m, RelativeObservation)]
        if vectors:
            parts.append(
                RelativePositionBatch(
                    np.array([self.layout.index(v.observer) for v in vectors], dtype=np.intp),
                    np.array([self.layout.index(v.target) for v in vectors], dtype=np.intp),
                    np.array([[v.dx, v.dy] for v in vectors]),
                    np.array([v.sigma for v in vectors]),
                    outlier_fraction=0.02 if outliers else 0.0,
                )
            )
        return StackedMeasurement(tuple(parts)) if parts else None

    def _los_sigmas(self, keys: list[str]) -> FloatArray:
        """Line-of-sight noise of each pair for the NLOS-aware model: :meth:`_pair_sigma` on
        ``los_sigma`` (``_pair_ranges`` uses ``sigma_uwb``). Keys ``""`` (corrected upstream)
        get the symmetric model from the caller; online biases never come here."""
        los = self.config.filter.los_sigma
        return np.array([self._pair_sigma(key, los) if key else los for key in keys])

    def _positions(
        self, mean: FloatArray, cov: FloatArray
    ) -> tuple[dict[str, tuple[float, float]], dict[str, tuple[tuple[float, float], tuple[float, float]]]]:
        """Per non-reference robot, its mean ``(x, y)`` and covariance as nested tuples, from
        ``(N-1, 2)`` means and ``(N-1, 2, 2)`` covariances."""
        positions, covs = {}, {}
        for k, robot in enumerate(self.layout.others):
            positions[robot] = (float(mean[k, 0]), float(mean[k, 1]))
            c = cov[k]
            covs[robot] = ((float(c[0, 0]), float(c[0, 1])), (float(c[1, 0]), float(c[1, 1])))
        return positions, covs

    def _estimate(self, t: float) -> Estimate:
        fe = self.pf.estimate()
        positions, covs = self._positions(fe.mean, fe.cov)
        biases: dict[str, tuple[float, float]] = {}
        if self.online_bias:
            w = np.exp(self.pf.logw)
            for pair in self.layout.bias_pairs:
                c, _ = self.layout.bias_columns(pair)
                biases[pair] = mixture_moments(w, self.pf.particles[:, c], self.pf.particles[:, c + 1])
        est = Estimate(t, self.method, self.layout.reference, positions, covs, fe.ess, biases=biases)
        self.last_estimate = est
        return est


class MultilaterationLocalizer(Localizer):
    """Least-squares formation from the latest range of every pair, gauge kept continuous."""

    method = "multilateration"

    def __init__(self, config: TeamConfig, *, max_age: float = 0.5, seed: int = 0) -> None:
        super().__init__(config)
        self.max_age = max_age
        self._latest: dict[tuple[int, int], tuple[float, float]] = {}  # pair -> (t, corrected d)
        self._previous: FloatArray | None = None
        self.rng = np.random.default_rng(seed)

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        pairs, dist, bias, _, _ = self._pair_ranges(batch)
        for key, d, b in zip(pairs, dist, bias, strict=True):
            self._latest[key] = (t, max(d - b, 0.0))
        fresh = {k: d for k, (tk, d) in self._latest.items() if t - tk <= self.max_age}
        n = len(self.layout.robots)
        ref = self.layout.index(self.layout.reference)
        if not fresh:
            self.stats["no_estimate"] += 1
            return None
        keys = np.array(list(fresh), dtype=np.intp)
        sol = multilateration.solve(n, ref, keys, np.array(list(fresh.values())), self._previous, self.rng)
        if sol is None:
            self.stats["no_estimate"] += 1
            return None
        self._previous = sol
        positions = {r: (float(sol[self.layout.index(r), 0]), float(sol[self.layout.index(r), 1])) for r in self.layout.others}
        return Estimate(t, self.method, self.layout.reference, positions)
