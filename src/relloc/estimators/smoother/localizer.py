"""The fixed-lag smoother (``[filter] kind = "smoother"``): a factor graph of the team's positions.

For teams where UWB ranges dominate (robots without odometry, large teams). Every
``STEP_PERIOD`` the smoother (:class:`relloc.estimators.smoother.graph.GraphSmoother`, GTSAM's
iSAM2 over a ``LAG`` window) gets one key per robot and:

* per pair ranged in the step, one Huber-robust range factor: the median of the bias-corrected
  ranges, the pair's noise undivided (a step's ranges share their bias error);
* per robot, a between factor: its odometry displacement in the shared heading frame, or
  without odometry a random walk of ``UNKNOWN_SPEED``, each robot's own;
* per observer and target, a Huber-robust between factor of their measured relative position
  (sightings with a range and a bearing, in the shared frame by the observer's yaw; detections'
  relative observations): the step's median vector, its noise undivided.

**Tags**: a robot with several UWB tags is a point per tag, held at its lever arms' distance,
each moved by its robot's odometry and its arm turned by the odometry's turn; the published
robot is their rigid fit (:mod:`relloc.filter.tag_points`).

**Start** (:mod:`.start`): the range graph's shape; with
odometry ``start.ROTATIONS`` rotations times two reflections each start a smoother, pruned by cost
(``PRUNE_COST``, then the best after ``HYPOTHESIS_TIME``); without, the rotation/reflection is
a gauge the random walks hold (``orientation_observable = False``, ring moments, the shape in
the smoother's own frame). Without ranges: the relative positions chained from the reference.

**Stamps**: a step's keys are at the batch's time; in a team where no robot reports odometry at
the median time of the step's ranges, since nothing carries the motion past them.

**Estimate**: each robot's latest key less the reference's, covariance from their joint
marginal; online biases (a constant key per node pair, shared offsets:
:class:`~relloc.localizers.priors.BiasPrior`) from their marginals. GTSAM's ``RuntimeError``
or the watchdog's alarm restarts from the last ``RESTART_WINDOW`` of ranges, the online
biases' posterior carried as their prior. Headings and odometry scales are not estimated.
**Smoothed** (:meth:`SmootherLocalizer.smoothed_estimates`, after a run): each segment between
restarts optimised at once, scored as the row ``<method>_smoothed``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.estimate import OWN_FRAME, Estimate, covariance_of, position_of
from relloc.estimators.smoother.graph import GraphSmoother
from relloc.estimators.smoother.moments import flatten, moments, per_pair
from relloc.estimators.smoother.start import (
    chained_start,
    kept_by_cost,
    merge_fixes,
    range_start,
)
from relloc.events import RangeEvent
from relloc.filter.base import FilterEstimate
from relloc.filter.factors import RangeTerms, RelativeFix
from relloc.filter.measurement import ModelContext, hook
from relloc.filter.motion import PROCESS_NOISE
from relloc.filter.ranges import RangeBatch
from relloc.filter.registry import MODELS, model_for
from relloc.filter.summary import estimate_fields
from relloc.filter.tag_points import TagPoints
from relloc.localizers.base import Measurement
from relloc.localizers.calibration_check import calibration_check
from relloc.localizers.priors import ROTATION_FLOOR, bias_layout
from relloc.localizers.stepped import SteppedLocalizer

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

STEP_PERIOD = 0.5
"""Seconds between smoother steps (keys): ranges of a step are merged per pair."""
LAG = 10.0
"""Seconds of keys the smoother keeps; older ones are marginalised by GTSAM."""
UNKNOWN_SPEED = 0.5
"""Std (m/s per axis) of the relative motion of a robot whose (or whose reference's)
odometry is missing: the speed a ground robot of the team stays under."""
ODOMETRY_FLOOR = 0.01
"""Smallest std (m per axis) of a step's relative odometry displacement."""
PRUNE_COST = 10.0
"""A hypothesis whose graph error exceeds the best's by this much is dropped (error is half
the chi-square: a likelihood ratio of e^-10)."""
HYPOTHESIS_TIME = 15.0
"""Seconds after the start after which only the best hypothesis is kept."""
MOTION_TO_RESOLVE = 0.3
"""Relative odometry displacement (m) of some robot after which the orientation counts as
observed (:mod:`relloc.filter.summary`)."""
RESTART_WINDOW = 2.0
"""Seconds of ranges a restart builds its start from."""


@dataclasses.dataclass
class _Segment:
    """The steps published between two restarts: the hypothesis whose record holds them (the
    best at the last one), their smoother step numbers and their causal estimates."""

    smoother: GraphSmoother
    steps: list[int] = dataclasses.field(default_factory=list)
    estimates: list[Estimate] = dataclasses.field(default_factory=list)


class SmootherLocalizer(SteppedLocalizer):
    """Odometry, UWB ranges and relative positions in a fixed-lag factor-graph smoother
    (module docstring)."""

    method = "pf"
    range_model = "symmetric"

    def __init__(self, config: TeamConfig, *, seed: int = 0, method: str = "pf") -> None:
        layout, prior = bias_layout(config, uncalibrated_sigma=config.uwb.default_bias_sigma)
        super().__init__(config, layout, seed=seed)
        self._bias_prior = prior
        self.calibration_check = calibration_check(config, prior)
        self._bias_of_column = {
            layout.bias_belief_column(p): j for j, p in enumerate(layout.bias_pairs)
        }
        self._pair_bias: dict[tuple[int, int], int] = {}
        """Point pair -> its online bias (pairs with a fixed bias are not in it)."""
        self._points = TagPoints.of(config, self.layout)
        """The graph's points: the robots, or a robot's tags where it has several."""
        self.method = method
        self._context = ModelContext(
            config,
            self.layout,
            range_model="symmetric",
            yaw_at=lambda robot, t: self.odometry.pose(robot, t)[2],
        )
        self._no_factors = [
            cls.stat
            for cls in dict.fromkeys(MODELS.values())
            if cls is not RangeBatch and hook(cls, "fixes")([], self._context) is None
        ]
        """The registered sensors the smoother takes no factors from (said at the start)."""
        if self._no_factors:
            log.warning(
                "the smoother uses no %s measurements: they are counted as smoother_<name>_unused",
                ", ".join(self._no_factors),
            )
        lay = self.layout
        self._ref = lay.index(lay.reference)
        self._ref_point = self._points.reference_point
        self._others = np.array([lay.index(r) for r in lay.others], dtype=np.intp)
        self.hypotheses: list[GraphSmoother] = []
        self._placed = np.zeros(self._points.size, dtype=bool)
        self._pending: dict[tuple[int, int], list[tuple[float, float]]] = {}
        self._range_times: list[float] = []
        self._ranges_only = not any(r.odom_topic for r in config.robots)
        """No robot reports odometry: each step's key (and estimate) is stamped at the median
        time of its ranges, which nothing could carry to the batch's time."""
        self._step_batch: list[Measurement] = []
        self._recent: deque[RangeEvent] = deque()
        self._pending_rel: list[RelativeFix] = []
        """The step's measured relative positions (:meth:`_observations`)."""
        self._recent_rel: deque[tuple[float, RelativeFix]] = deque()
        self._moved = np.zeros(self._others.size)
        self._t_start = math.nan
        self._observable = False
        self._started_with = 0
        self._segments: list[_Segment] = []
        self._open: _Segment | None = None
        self._smoothed: tuple[int, list[Estimate]] | None = None

    @property
    def smoother(self) -> GraphSmoother | None:
        """The best hypothesis's smoother (``None`` before the start)."""
        return self.hypotheses[0] if self.hypotheses else None

    def _shift_time(self, dt: float) -> None:
        super()._shift_time(dt)
        self._t_start += dt

    # ---------------------------------------------------------------- ranges
    def _ranges(self, events: list[RangeEvent]) -> RangeTerms:
        """The range terms of ``events`` (per 0.1 s batch: the median per pair,
        :meth:`RangeBatch.build`; an online bias is the graph's, noted in ``_pair_bias``)."""
        models = [b for b in RangeBatch.build(events, self._context) if isinstance(b, RangeBatch)]
        if not models:
            return RangeTerms.empty()
        ia = np.concatenate([self._points.points_of(b.index_a, b.nodes, 0) for b in models])
        ib = np.concatenate([self._points.points_of(b.index_b, b.nodes, 1) for b in models])
        start = 0
        for b in models:
            if b.bias_columns is not None:
                rows = zip(
                    ia[start : start + len(b)].tolist(),
                    ib[start : start + len(b)].tolist(),
                    b.bias_columns.tolist(),
                    strict=True,
                )
                for a, c, col in rows:
                    if col >= 0:
                        self._pair_bias[(min(a, c), max(a, c))] = self._bias_of_column[col]
            start += len(b)
        z = np.maximum(np.concatenate([b.distance - b.bias for b in models]), 0.0)
        s = np.concatenate([b.sigma for b in models])
        return RangeTerms(ia, ib, z, s, self._bias_index(ia, ib))

    def _observations(self, batch: list[Measurement]) -> list[RelativeFix]:
        """The relative positions ``batch``'s measurement models give a factor graph
        (:meth:`MeasurementModel.fixes`: detections, sightings with a range and a bearing, a
        plug-in's); what a model gives none of is counted in ``smoother_<stat>_unused``."""
        groups: dict[type, list[Measurement]] = {}
        for m in batch:
            cls = model_for(m)
            if cls is not None and cls is not RangeBatch:
                groups.setdefault(cls, []).append(m)
        out: list[RelativeFix] = []
        for cls, events in groups.items():
            got = hook(cls, "fixes")(events, self._context)
            fixes, unused = ([], len(events)) if got is None else got
            first = self._points.first
            out += [
                dataclasses.replace(f, observer=int(first[f.observer]), target=int(first[f.target]))
                for f in fixes
            ]
            if unused:
                self.stats[f"smoother_{cls.stat}_unused"] += unused
        return out

    def _remember(self, t: float, batch: list[Measurement]) -> list[RangeEvent]:
        """Keep the last ``RESTART_WINDOW`` of ranges and relative positions (a restart's
        start); the new ranges, the step's relative positions into ``_pending_rel``."""
        ranges = [m for m in batch if model_for(m) is RangeBatch]
        self._recent.extend(ranges)
        while self._recent and self._recent[0].t < t - RESTART_WINDOW:
            self._recent.popleft()
        observed = self._observations(batch)
        self._pending_rel += observed
        self._recent_rel.extend((t, o) for o in observed)
        while self._recent_rel and self._recent_rel[0][0] < t - RESTART_WINDOW:
            self._recent_rel.popleft()
        return ranges

    # ---------------------------------------------------------------- the cycle
    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        if not self.initialized:  # the start window; a restart builds on it too
            self._remember(t, batch)
        return super()._step(t, batch)

    def _cycle(self, t: float, batch: list[Measurement]) -> Estimate | None:
        """The step's ranges merged per pair; every ``STEP_PERIOD`` a smoother step."""
        ranges = self._remember(t, batch)
        self._step_batch += batch
        terms = self._ranges(ranges)
        for a, b, z, s in zip(
            terms.index_a.tolist(),
            terms.index_b.tolist(),
            terms.distance.tolist(),
            terms.sigma.tolist(),
            strict=True,
        ):
            self._pending.setdefault((a, b), []).append((z, s))
        self._range_times += [m.t for m in ranges]
        if t - self.t < STEP_PERIOD:
            return None
        times, self._range_times = self._range_times, []
        if times and self._ranges_only:  # nothing carries the motion from the ranges to t
            t = max(float(np.median(times)), self.t + 1e-3)
        return self._advance(t)

    def _start(self, t: float, batch: list[Measurement]) -> Estimate | None:
        ranges = [m for m in batch if model_for(m) is RangeBatch]
        if not self._start_from(t, ranges, [o for _, o in self._recent_rel]):
            return None
        self._started(t)
        return self._emit(t, self._estimate())

    def _start_from(
        self,
        t: float,
        ranges: list[RangeEvent],
        observed: list[RelativeFix],
    ) -> bool:
        """Start the hypotheses at ``t`` from ``ranges``' graph, or where they place no robot
        from the ``observed`` relative positions alone (module docstring); False where
        neither places a robot."""
        terms = self._ranges(ranges)
        n = self._points.size
        relative = merge_fixes(observed)
        start = (
            range_start(
                n,
                self._ref_point,
                self._points.with_rigid(terms),
                self._bias_prior.marginal_mean,
                odometry=self._framed(t),
            )
            if terms.size
            else None
        )
        if start is None:
            start = chained_start(n, self._ref_point, observed)
            if start is None:
                return False
        means, covs, placed, rms = start
        merged = self._points.with_rigid(
            self._per_pair(terms.index_a, terms.index_b, terms.distance, terms.sigma)
        )
        self.hypotheses = []
        for m in range(means.shape[0]):
            smoother = GraphSmoother(
                n, self._ref_point, LAG, self._bias_prior, record=self.keeps_run
            )
            smoother.start(t, means[m], covs[m], ranges=merged, relative=relative)
            self.hypotheses.append(smoother)
        self._placed = placed
        self._pending = {}
        self._pending_rel = []
        self._step_batch = []
        self._moved[:] = 0.0
        self._t_start = t
        # a relative position in the shared frame fixes the orientation the ranges leave open
        # (a reference's tags do not: ranges never tell the formation from its mirror image)
        self._observable = relative is not None and means.shape[0] == 1 and self._framed(t)
        self._started_with = len(self.hypotheses)
        self.stats["smoother_hypotheses"] = len(self.hypotheses)
        self.stats["smoother_start_rms_mm"] = round(1000.0 * rms)
        return True

    def _framed(self, t: float) -> bool:
        """Whether some robot has odometry at ``t`` (the shared heading frame exists)."""
        return any(math.isfinite(self.odometry.pose(r, t)[0]) for r in self.layout.robots)

    def _advance(self, t: float) -> Estimate | None:
        disp, sigma = self._own_motion(t)
        pending, self._pending = self._pending, {}
        observed, self._pending_rel = self._pending_rel, []
        relative = merge_fixes(observed)
        merged = self._points.with_rigid(self._per_pair(*flatten(pending)))
        ia, ib, z = merged.index_a, merged.index_b, merged.distance
        reached = np.zeros(self._points.size, dtype=bool)
        reached[ia] = True
        reached[ib] = True
        newly = reached & ~self._placed
        batch, self._step_batch = self._step_batch, []
        survivors = []
        for smoother in self.hypotheses:
            guess = self._placement(smoother, newly, ia, ib, z)
            try:
                smoother.advance(t, disp, sigma, ranges=merged, guess=guess, relative=relative)
            except RuntimeError:
                self.stats["smoother_indeterminate"] += 1
                continue
            survivors.append(smoother)
        self._placed |= reached
        self.hypotheses = survivors
        if not survivors:
            return self._recover(t)
        self._prune(t)
        fe = self._estimate()
        yaws = {r: self.odometry.pose(r, t)[2] for r in self.layout.robots}
        if self.watchdog.observe(t, batch, fe, yaws):
            self.stats["inconsistency_restarts"] += 1
            return self._recover(t)
        self.stats["smoother_factors"] = self.hypotheses[0].size()
        return self._emit(t, fe)

    def _recover(self, t: float) -> Estimate | None:
        """Start again from the last ``RESTART_WINDOW`` of ranges (no hypothesis survived, or
        the watchdog found the covariance inconsistent)."""
        self.stats["smoother_restarts"] += 1
        self.watchdog.restart(t)
        if self._open is not None:
            self._carry_biases(self._open.smoother)
            if self.keeps_run:
                self._segments.append(self._open)
            self._open = None
        if not self._start_from(t, list(self._recent), [o for _, o in self._recent_rel]):
            self.initialized = False
            return None
        self._started(t)
        return self._emit(t, self._estimate())

    def _carry_biases(self, best: GraphSmoother) -> None:
        """What the run taught of the online biases, kept across a restart: the last best
        hypothesis's posterior becomes the prior (:meth:`BiasPrior.carried`); the prior stays
        where that posterior cannot be had (the graph that failed)."""
        carried = self._bias_prior.carried_from(best)
        if carried is not None:
            self._bias_prior = carried
            self.stats["smoother_biases_carried"] += 1

    def _own_motion(self, t: float) -> tuple[FloatArray, FloatArray]:
        """Each point's displacement since the last step ``(P, 2)`` and its per-axis std
        ``(P,)``: its robot's odometry's (module docstring), or none with ``UNKNOWN_SPEED``; a
        tag's plus its lever arm turned by the odometry's turn."""
        known = np.array(
            [not math.isnan(self._anchor.get(r, (math.nan,))[0]) for r in self.layout.robots]
        )
        yaw0 = None if self._points.identity else self._anchor_yaws()  # before the step
        disp, own, dt = self._motion_to(t)
        known &= np.array([math.isfinite(self.odometry.pose(r, t)[0]) for r in self.layout.robots])
        walk = np.where(known, PROCESS_NOISE**2 * dt + ODOMETRY_FLOOR**2, (UNKNOWN_SPEED * dt) ** 2)
        sigma = np.sqrt(own**2 + walk)
        ref = self._ref
        rel = disp[self._others] - disp[ref]
        both = known[self._others] & known[ref]
        self._moved += np.where(both, np.hypot(rel[:, 0], rel[:, 1]), 0.0)
        disp = np.where(known[:, None], disp, 0.0)
        if yaw0 is None:
            return disp, sigma
        robot, arm = self._points.robot, self._points.arm
        turned = _turned(arm, self._anchor_yaws()[robot]) - _turned(arm, yaw0[robot])
        return disp[robot] + np.where(known[robot][:, None], turned, 0.0), sigma[robot]

    def _anchor_yaws(self) -> FloatArray:
        """Each robot's odometry yaw at the last step (0 before its first odometry)."""
        return np.array([self._anchor.get(r, (0.0, 0.0, 0.0))[2] for r in self.layout.robots])

    def _per_pair(
        self, ia: NDArray[np.intp], ib: NDArray[np.intp], z: FloatArray, s: FloatArray
    ) -> RangeTerms:
        """One range term per pair (:func:`per_pair`) with its online bias."""
        pa, pb, pz, ps = per_pair(ia, ib, z, s)
        return RangeTerms(pa, pb, pz, ps, self._bias_index(pa, pb))

    def _bias_index(self, ia: NDArray[np.intp], ib: NDArray[np.intp]) -> NDArray[np.intp]:
        """Per range (team indices) its online bias, -1 where its bias is fixed."""
        pairs = zip(np.minimum(ia, ib).tolist(), np.maximum(ia, ib).tolist(), strict=True)
        return np.array([self._pair_bias.get(p, -1) for p in pairs], dtype=np.intp)

    def _placement(
        self,
        smoother: GraphSmoother,
        newly: NDArray[np.bool_],
        ia: NDArray[np.intp],
        ib: NDArray[np.intp],
        z: FloatArray,
    ) -> FloatArray | None:
        """Initial guesses for robots a range reaches for the first time: at the range's
        distance from the robot it connects to (a range factor cannot start from coinciding
        points); ``None`` when there are none."""
        if not newly.any():
            return None
        guess = smoother.positions.copy()
        for a, b, d in zip(ia.tolist(), ib.tolist(), z.tolist(), strict=True):
            for new, other in ((a, b), (b, a)):
                if newly[new] and not newly[other]:
                    base = smoother.positions[other]
                    angle = 2.399963 * (new + 1)  # the golden angle: distinct directions
                    guess[new] = base + max(d, 0.1) * np.array([math.cos(angle), math.sin(angle)])
        return guess

    def _prune(self, t: float) -> None:
        """Drop hypotheses the graph error has ruled out (module docstring)."""
        if len(self.hypotheses) > 1:
            costs = np.array([h.cost() for h in self.hypotheses])
            keep = kept_by_cost(costs, PRUNE_COST, t - self._t_start >= HYPOTHESIS_TIME)
            self.hypotheses = [self.hypotheses[i] for i in keep]
            self.stats["smoother_hypotheses"] = len(self.hypotheses)
            if len(self.hypotheses) == 1:
                self._observable = bool(self._moved.max(initial=0.0) >= MOTION_TO_RESOLVE)
        elif not self._observable and self._started_with > 1:
            self._observable = bool(self._moved.max(initial=0.0) >= MOTION_TO_RESOLVE)

    # ---------------------------------------------------------------- the estimate
    def _estimate(self) -> FilterEstimate:
        """The best hypothesis's latest positions, covariances and summary as published
        (:func:`relloc.estimators.smoother.moments.moments`), with the online biases."""
        best = self.hypotheses[0]
        if self._points.identity:
            rel, rel_cov = best.estimate.copy(), best.covariances()
            yaws: dict[str, tuple[float, float]] = {}
        else:
            rel, rel_cov, yaws = self._robots(best.positions, best.point_joint())
        floor = 0.0 if self._points.oriented else ROTATION_FLOOR
        mean, cov, summary = moments(rel, rel_cov, self._observable, floor)
        biases = {
            pair: (float(m), float(sd))
            for pair, m, sd in zip(
                self.layout.bias_pairs, best.biases.tolist(), best.bias_std().tolist(), strict=True
            )
        }
        offsets = dict(
            zip(
                self._bias_prior.latents,
                zip(*best.offset_estimates(), strict=True),
                strict=True,
            )
        )
        return FilterEstimate(
            mean,
            cov,
            None,  # no weighted particles: the hypotheses are counted in smoother_hypotheses
            biases=biases,
            offsets=offsets,
            summary=summary,
            particles=len(self.hypotheses),
            yaws=yaws,
        )

    def _robots(
        self, points: FloatArray, joint: FloatArray
    ) -> tuple[FloatArray, FloatArray, dict[str, tuple[float, float]]]:
        """A team with multi-tag robots: the non-reference robots' positions ``(N-1, 2)`` and
        covariances from the graph's absolute point positions and their joint covariance, and
        the multi-tag robots' headings relative to the reference's
        (:mod:`relloc.filter.tag_points`)."""
        pts = self._points
        rel, cov, heads, stds = pts.moments(points, joint, body=self._observable)
        if not self._observable:  # a heading's sign flips with the formation's mirror image
            return rel, cov, {}
        robots = self.layout.robots
        yaws = {
            robots[r]: (float(h), float(sd))
            for r, h, sd in zip(pts.heading_robots(), heads.tolist(), stds.tolist(), strict=True)
        }
        return rel, cov, yaws

    def _emit(self, t: float, fe: FilterEstimate, body: FilterEstimate | None = None) -> Estimate:
        if body is None and self._points.oriented and self._observable:
            body = fe  # the positions are in the reference's body frame its tags observe
        est = super()._emit(t, fe, body)
        if not est.orientation_observable:
            est = dataclasses.replace(est, shape_gauge=OWN_FRAME)
            self.last_estimate = est
        best = self.hypotheses[0]
        if self._open is None:
            self._open = _Segment(best)
        self._open.smoother = best
        if self.keeps_run:
            self._open.steps.append(best.step)
            self._open.estimates.append(est)
        return est

    # ---------------------------------------------------------------- the smoothed run
    def smoothed_estimates(self) -> list[Estimate]:
        """The whole run smoothed: one estimate per published step (``[]`` before the start),
        each segment between restarts smoothed on its own (:meth:`GraphSmoother.batch` of the
        hypothesis that was best at its end; the ranges before a restart do not reach past it).

        Positions and covariances are the batch graph's; the orientation counts as observed
        over a whole segment once it was at its end (the batch holds the motion that resolved
        it, and the losing hypotheses are gone); else ring moments and the shape in the
        smoother's own frame, as :meth:`_estimate`. The other fields (flags, unseen robots) are
        the causal estimate's; the covariances are not widened. A segment whose batch is
        indeterminate keeps its causal estimates. Cached until a step is published; never
        computed while serving unless called."""
        if not self.keeps_run:
            return []
        segments = [*self._segments, *([] if self._open is None else [self._open])]
        count = sum(len(s.steps) for s in segments)
        if self._smoothed is None or self._smoothed[0] != count:
            out: list[Estimate] = []
            for segment in segments:
                out += self._smooth(segment)
            self._smoothed = (count, out)
        return list(self._smoothed[1])

    def _smooth(self, segment: _Segment) -> list[Estimate]:
        try:
            if self._points.identity:
                means, covs = segment.smoother.batch(segment.steps)
                assert covs is not None
                yaws: list[dict[str, tuple[float, float]]] = [{} for _ in segment.steps]
            else:
                points, joints = segment.smoother.batch_joint(segment.steps)
                robots = [self._robots(p, j) for p, j in zip(points, joints, strict=True)]
                means = np.array([r[0] for r in robots])
                covs = np.array([r[1] for r in robots])
                yaws = [r[2] for r in robots]
        except RuntimeError:
            return list(segment.estimates)
        observable = segment.estimates[-1].orientation_observable
        others = self.layout.others
        out = []
        floor = 0.0 if self._points.oriented else ROTATION_FLOOR
        for causal, mean, cov, yaw in zip(segment.estimates, means, covs, yaws, strict=True):
            mean, cov, summary = moments(
                mean, cov, observable or causal.orientation_observable, floor
            )
            fields = estimate_fields(summary, self.layout.reference, others)
            if not summary.orientation_observable:
                fields["shape_gauge"] = OWN_FRAME
            positions = {r: position_of(mean[k]) for k, r in enumerate(others)}
            covariances = {r: covariance_of(cov[k]) for k, r in enumerate(others)}
            out.append(
                dataclasses.replace(
                    causal, positions=positions, covariances=covariances, yaws=yaw, **fields
                )
            )
        return out


def _turned(arm: FloatArray, yaw: FloatArray) -> FloatArray:
    """Each lever arm ``(P, 2)`` turned by its robot's yaw ``(P,)``."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * arm[:, 0] - s * arm[:, 1], s * arm[:, 0] + c * arm[:, 1]], axis=1)
