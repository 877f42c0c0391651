"""The 3D smoother (``[filter] kind = "smoother3d"``): a flying team's level poses in a
fixed-lag factor graph.

Every ``STEP_PERIOD`` one ``Pose3`` key per robot (:class:`.graph.PoseWindow`) gets:

* its odometry since the last step (pose messages in the robot's own frame, with their z) as
  a displacement in its body frame and a turn, with stds that grow with the motion; without
  odometry a random walk of ``UNKNOWN_SPEED`` and ``UNKNOWN_TURN_RATE`` and, over its last
  three keys, a constant velocity (:mod:`.graph`);
* per tag pair ranged in the step, the median of its bias-corrected ranges, its noise
  undivided (a step's ranges share their error); in a team without odometry the step's keys
  are stamped at the median measurement time of its ranges (stamp minus ``uwb.range_delay``),
  since nothing carries the motion past them, and the next step comes once the newest range is
  ``STEP_PERIOD`` past that stamp: with a delay near the period, at every batch of ranges
  (about 10 Hz on ``drones_six``; a fixed 0.1 s was worse there: docs/explanation/flying.md);
* per robot with heights in the step (:class:`~relloc.events.HeightEvent`), their median.

**Start** (:mod:`.start`): level poses from the start window's ranges and heights, one
hypothesis per handedness (and per reference yaw where the reference has one tag), each its
own smoother, pruned by graph cost (``PRUNE_COST``; the best after ``HYPOTHESIS_TIME``).
Ranges never tell a formation from its mirror image; odometry does once the robots moved
``MOTION_TO_RESOLVE`` relative to the reference: the orientation is observable then, not
before (nor ever without odometry).

**Estimate**: every other robot's position ``(x, y, z)`` and yaw in the reference's level
body frame with their covariances (:meth:`.graph.PoseWindow.relative`), the online biases
(:class:`~relloc.localizers.priors.BiasPrior`, as the 2D smoother's). Sightings and detections
are counted as ``smoother3d_<stat>_unused``. GTSAM's ``RuntimeError`` restarts from the last
``RESTART_WINDOW`` of ranges. **Smoothed** (:meth:`~PoseSmootherLocalizer.smoothed_estimates`,
the row ``<method>_smoothed``): each published step as the window saw it ``SMOOTH_DELAY`` later.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.estimate import BODY_FRAME, OWN_FRAME, Estimate, covariance_of, position_of
from relloc.estimators.smoother.start import kept_by_cost
from relloc.estimators.smoother3d.graph import Motion, PoseWindow, TagRanges, pose_of
from relloc.estimators.smoother3d.start import (
    YAW_TRUST,
    chiral,
    in_reference_frame,
    level_start,
    yaws_from_motion,
)
from relloc.events import Event, HeightEvent, OdometryEvent, RangeEvent, pair_key
from relloc.filter.measurement import ModelContext, finite
from relloc.filter.ranges import RangeBatch
from relloc.filter.registry import model_for
from relloc.localizers.base import Localizer, Measurement
from relloc.localizers.priors import bias_layout
from relloc.odometry import wrap_angle

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

STEP_PERIOD = 0.5
"""Seconds between smoother steps."""
LAG = 10.0
"""Seconds of keys the smoother keeps."""
UNKNOWN_SPEED = 1.0
"""Std (m/s per axis) of the motion of a robot without odometry: what a small drone stays
under indoors."""
UNKNOWN_TURN_RATE = 1.0
"""Std (rad/s) of the turn of a robot without odometry."""
ODOMETRY_RELATIVE = 0.02
"""Std of an odometry displacement per metre moved."""
TURN_RELATIVE = 0.01
"""Std of an odometry turn per radian turned (a gyro's scale error)."""
ODOMETRY_WALK = 0.02
"""Std (m/sqrt(s) per axis) of the odometry's drift while hovering."""
YAW_WALK = 0.003
"""Std (rad/sqrt(s)) of the odometry yaw's drift (a gyro's)."""
ODOMETRY_FLOOR = 0.01
"""Smallest std (m per axis) of a step's odometry displacement."""
TURN_FLOOR = 0.002
"""Smallest std (rad) of a step's odometry turn."""
HEIGHT_FLOOR = 0.02
"""Smallest std (m) of a step's height."""
PRUNE_COST = 10.0
"""A hypothesis whose graph error exceeds the best's by this much is dropped."""
HYPOTHESIS_TIME = 15.0
"""Seconds after the start after which only the best hypothesis is kept."""
MOTION_TO_RESOLVE = 0.3
"""Odometry displacement (m) relative to the reference after which the mirror image is
resolved."""
MOTION_YAW_SIGMA = 0.2
"""Std (rad) of a yaw taken from motion."""
POSITION_SIGMA = 0.3
"""Std (m per axis) of a robot's position when its yaws from motion restart the window."""
MOTION_TO_PRUNE = 2.0
"""Odometry displacement (m) of every robot with odometry before hypotheses are pruned by cost:
enough for a turn of the formation to show against the pair biases' prior."""
RESTART_WINDOW = 2.0
"""Seconds of ranges a restart builds its start from."""
SMOOTH_DELAY = 5.0
"""Seconds after a step at which the smoothed run takes its poses from the window (half the
lag: the step's keys are still in it)."""
CHOOSE_PERIOD = 1.0
"""Seconds between choices of the hypothesis published while several are kept (their graphs'
errors cost about as much as their steps)."""


class PoseSmootherLocalizer(Localizer):
    """Odometry, heights and tag ranges of a flying team in a fixed-lag smoother of level
    poses (module docstring)."""

    method = "pf"

    def __init__(self, config: TeamConfig, *, seed: int = 0, method: str = "pf") -> None:
        layout, prior = bias_layout(config, uncalibrated_sigma=config.uwb.default_bias_sigma)
        super().__init__(config, layout)
        self.method = method
        self._prior = prior
        self._bias_of_column = {
            layout.bias_belief_column(p): j for j, p in enumerate(layout.bias_pairs)
        }
        self._context = ModelContext(config, layout, range_model="symmetric", shared_heading=False)
        robots = self.layout.robots
        tags = [(i, t) for i, r in enumerate(robots) for t in config.robot(r).tag_list]
        self._tag_robot = np.array([i for i, _ in tags], dtype=np.intp)
        self._arms = np.array([(*t.lever_arm, 0.0)[:3] for _, t in tags], float).reshape(-1, 3)
        self._tag_of = {t.node: k for k, (_, t) in enumerate(tags)}
        self._first_tag = {robots[i]: k for k, (i, _) in reversed(list(enumerate(tags)))}
        self._ref = self.layout.index(self.layout.reference)
        self._has_odometry = any(r.odom_topic for r in config.robots)
        self._gyros = np.array([bool(config.robot(r).odom_topic) for r in robots])
        """Robots whose odometry turns carry a gyro bias the window estimates."""
        self._heights: dict[str, deque[tuple[float, float, float]]] = {r: deque() for r in robots}
        self._odom_z: dict[str, tuple[list[float], list[float]]] = {r: ([], []) for r in robots}
        """Each robot's odometry heights: their times and values (the last ``2 LAG``)."""
        self._yaw_sigma = self._tag_yaw_sigma()
        mine = self._tag_robot == self._ref
        self._chiral = chiral(np.zeros(int(mine.sum()), np.intp), self._arms[mine])
        """Whether the reference's own tags tell the formation from its mirror image."""
        self.hypotheses: list[PoseWindow] = []
        self._unsmoothed: deque[tuple[int, Estimate]] = deque()
        """The published steps not yet smoothed, with their causal estimates."""
        self._smoothed: list[Estimate] = []
        self._published: tuple[PoseWindow, float] | None = None
        """The hypothesis published while several are kept, and when it was chosen."""
        self.initialized = False
        self.t = math.nan
        self._t_start = math.nan
        self._init: list[RangeEvent] = []
        self._recent: deque[RangeEvent] = deque()
        self._pending: list[RangeEvent] = []
        self._anchor: dict[str, tuple[float, float, float, float]] = {}
        self._moved = 0.0
        self._moved_each = np.zeros(len(robots))
        self._observable = False
        self._finding = False
        """Whether ranges alone place the robots while their yaws are sought from motion."""
        self._track: list[tuple[int, FloatArray]] = []

    def _track_frame(self, robot: str) -> tuple[float, float]:
        """Each robot's odometry in its own frame (its heading is estimated), at its scale."""
        return 0.0, self.config.robot(robot).odom_scale

    # ---------------------------------------------------------------- events
    def process(self, event: Event) -> list[Estimate]:
        """Heights are kept for the steps; odometry's z beside its track; the rest as every
        localizer's."""
        if isinstance(event, HeightEvent):
            reason = self._height_rejection(event)
            if reason is not None:
                self._reject(reason, event)
            else:
                self._heights[event.robot].append((event.t, event.z, event.sigma))
                self.stats["height"] += 1
            return []
        out = super().process(event)
        if isinstance(event, OdometryEvent) and event.robot in self._odom_z:
            track = self.odometry.tracks[event.robot]
            if track.last_event is event:
                times, values = self._odom_z[event.robot]
                times.append(event.t)
                values.append(event.z)
                if len(times) > 64 and times[0] < event.t - 2.0 * LAG:
                    cut = bisect.bisect_left(times, event.t - 2.0 * LAG)
                    del times[:cut], values[:cut]
        return out

    def _height_rejection(self, event: HeightEvent) -> str | None:
        if event.robot not in self.layout.robots:
            return "unknown_robot"
        if not (finite(event.t) and finite(event.z) and finite(event.sigma)) or event.sigma <= 0:
            return "invalid_height"
        return None

    # ---------------------------------------------------------------- the cycle
    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        ranges = [m for m in batch if model_for(m) is RangeBatch]
        for m in batch:
            cls = model_for(m)
            if cls is not None and cls is not RangeBatch:
                self.stats[f"smoother3d_{cls.stat}_unused"] += 1
        self._recent.extend(ranges)
        while self._recent and self._recent[0].t < t - RESTART_WINDOW:
            self._recent.popleft()
        if not self.initialized:
            self._init += ranges
            if not self._init or t - self._init[0].t < self.config.filter.init_window:
                return None
            start, self._init = self._init, []
            return self._start(t, start)
        self._pending += ranges
        if t - self.t < STEP_PERIOD:
            return None
        if self._pending and not self._has_odometry:  # nothing carries the motion to t
            measured = float(np.median([m.t for m in self._pending])) - self.config.uwb.range_delay
            t = max(measured, self.t + 1e-3)
        return self._advance(t)

    def _start(self, t: float, ranges: list[RangeEvent]) -> Estimate | None:
        terms = self._tag_ranges(ranges, t, prior_bias=True)
        if terms.size == 0:
            return None
        heights = np.array([self._height_at(r, t - 2.0 * RESTART_WINDOW, t) for r in self._names])
        known = {i: (float(h), HEIGHT_FLOOR) for i, h in enumerate(heights) if np.isfinite(h)}
        started = level_start(
            self._tag_robot,
            self._arms,
            heights,
            (terms.tag_a, terms.tag_b, terms.distance),
            self._ref,
            self._yaw_sigma,
        )
        if started is None:
            return None
        poses, sigma, rms = started
        terms = self._tag_ranges(ranges, t, prior_bias=False)
        # tags that fix no yaw well, and odometry to fix them: the reference's odometry and
        # the ranges place the others first, their motion then gives their yaws
        self._finding = bool(self._gyros[self._ref]) and bool(
            np.any(self._yaw_sigma[self._gyros] > YAW_TRUST)
        )
        self._start_windows(t, poses, sigma, terms, known)
        self._track = []
        if self._finding:
            self._record(t)
        self.initialized = True
        self.t = self._t_start = t
        self._anchor = {r: self._odometry(r, t) for r in self._names}
        self._moved = 0.0
        self._moved_each[:] = 0.0
        self._observable = False
        self.stats["smoother_hypotheses"] = len(self.hypotheses)
        self.stats["smoother_start_rms_mm"] = round(1000.0 * rms)
        return self._estimate(t)

    def _start_windows(
        self,
        t: float,
        poses: FloatArray,
        sigma: FloatArray,
        terms: TagRanges,
        heights: dict[int, tuple[float, float]],
    ) -> None:
        """One window per hypothesis ``poses`` ``(M, N, 4)`` (stds ``sigma``), started at ``t``
        with ``terms`` and ``heights``; without odometry's turns while the yaws are sought."""
        gyros = None if self._finding else self._gyros
        self._smooth(math.inf)  # the old windows' last word on their steps
        self.hypotheses = []
        for m in range(poses.shape[0]):
            window = PoseWindow(
                len(self._names), self._ref, LAG, self._prior, gyros, blind=~self._gyros
            )
            window.start(t, poses[m], sigma[m], ranges=terms, heights=heights)
            self.hypotheses.append(window)

    def _record(self, t: float) -> None:
        """Keep every robot's odometry ``(x, y, yaw)`` at the window's latest step (the yaws
        from motion)."""
        odometry = np.array([np.array(self._odometry(r, t))[[0, 1, 3]] for r in self._names])
        self._track.append((self.hypotheses[0].step, odometry))

    def _from_motion(
        self, t: float, terms: TagRanges, heights: dict[int, tuple[float, float]]
    ) -> None:
        """The yaws from motion (:func:`yaws_from_motion`): the window of ranges alone ends,
        one of poses starts at ``t`` with the yaws its placements and the odometry give, its
        biases' prior the posterior so far."""
        window = self.hypotheses[0]
        rows = [(window.positions_at(step), odometry) for step, odometry in self._track]
        kept = [(p[:, :2], o) for p, o in rows if p is not None]
        positions = np.array([p for p, _ in kept])
        odometry = np.array([o for _, o in kept])
        moving = self._gyros & np.all(np.isfinite(odometry), axis=(0, 2))
        moving[self._ref] = False  # its odometry holds the window's frame
        yaws, mirror, rms = yaws_from_motion(positions, odometry, moving)
        now = window.poses.copy()
        if mirror:
            now[:, 1] *= -1.0
            now[:, 3] *= -1.0
        now[moving, 3] = yaws[moving]
        poses = in_reference_frame(now, self._ref)
        sigma = np.tile(
            [POSITION_SIGMA, POSITION_SIGMA, POSITION_SIGMA, MOTION_YAW_SIGMA],
            (len(self._names), 1),
        )
        sigma[~moving, 3] = np.minimum(self._yaw_sigma[~moving], math.pi)
        self._carry_biases(window)
        self._finding = False
        self._track = []
        self._start_windows(t, poses[None], sigma[None], terms, heights)
        self._moved_each[:] = 0.0
        self.stats["smoother_yaws_from_motion_rms_mm"] = round(1000.0 * rms)

    def _carry_biases(self, window: PoseWindow) -> None:
        """The online biases' posterior so far becomes their prior (as the 2D smoother's
        restarts keep it: :meth:`BiasPrior.carried_from`)."""
        carried = self._prior.carried_from(window)
        if carried is not None:
            self._prior = carried

    def _advance(self, t: float) -> Estimate | None:
        motion = self._motion(t)
        if self._finding:  # the others walk while their yaws are sought
            walk = self._walk(motion.dt)
            others = np.arange(len(self._names)) != self._ref
            motion.delta[others] = walk.delta[others]
            motion.sigma[others] = walk.sigma[others]
            motion.measured[others] = False
        pending, self._pending = self._pending, []
        terms = self._tag_ranges(pending, t, prior_bias=False)
        heights = self._step_heights(self.t, t)
        self.t = t
        survivors = []
        for window in self.hypotheses:
            try:
                window.advance(t, motion, ranges=terms, heights=heights)
            except RuntimeError:
                self.stats["smoother_indeterminate"] += 1
                continue
            survivors.append(window)
        self.hypotheses = survivors
        if not survivors:
            return self._restart(t)
        self._prune(t)
        if self._finding:
            self._record(t)
            moved = self._moved_each[self._gyros].min() >= MOTION_TO_PRUNE
            late = t - self._t_start >= 2.0 * HYPOTHESIS_TIME
            if len(self.hypotheses) == 1 and (moved or late):
                self._from_motion(t, terms, heights)
                self._observable = self._moved >= MOTION_TO_RESOLVE
        return self._estimate(t)

    def _restart(self, t: float) -> Estimate | None:
        self.stats["smoother_restarts"] += 1
        self.initialized = False
        return self._start(t, list(self._recent))

    def _prune(self, t: float) -> None:
        """Keep the hypotheses within ``PRUNE_COST`` of the best once every robot with
        odometry moved ``MOTION_TO_PRUNE`` (before, the pair biases' prior, not the
        orientation, orders their costs), the best alone after ``HYPOTHESIS_TIME``; in a team
        without odometry, every hypothesis until then."""
        moved = self._moved_each[[self._ref] if self._finding else self._gyros]
        late = t - self._t_start >= HYPOTHESIS_TIME
        # without odometry the first steps' costs are ordered by the pair biases' prior and the
        # windows' first linearisations, not by the orientation (a tenfold PRUNE_COST still
        # dropped the right hypothesis on one seed of three of drones_six): all are kept
        enough = moved.size > 0 and moved.min() >= MOTION_TO_PRUNE
        if len(self.hypotheses) > 1 and (enough or late):
            costs = np.array([h.cost() for h in self.hypotheses])
            keep = kept_by_cost(costs, PRUNE_COST, late)
            self.hypotheses = [self.hypotheses[i] for i in keep]
            self.stats["smoother_hypotheses"] = len(self.hypotheses)
        self._observable = len(self.hypotheses) == 1 and (
            self._chiral  # the reference's tags tell the mirror image
            or (self._has_odometry and not self._finding and self._moved >= MOTION_TO_RESOLVE)
        )

    def _tag_yaw_sigma(self) -> FloatArray:
        """Per robot, the std of the yaw its tags give at the start: the std of the difference
        of its two farthest tags' ranges to another tag (the range noise, and the bias prior
        where the biases are online) over their span; ``pi`` for a robot with one tag."""
        out = np.full(len(self._names), math.pi)
        prior = self._prior
        cov = prior.covariance
        column = {p: j for j, p in enumerate(prior.pairs)}
        nodes = list(self._tag_of)
        noise = self.config.uwb.sigma
        for r in range(len(self._names)):
            mine = np.flatnonzero(self._tag_robot == r)
            if mine.size < 2:
                continue
            flat = self._arms[mine, :2]
            gaps = np.linalg.norm(flat[:, None] - flat[None], axis=2)
            i, j = np.unravel_index(int(np.argmax(gaps)), gaps.shape)
            span = float(gaps[i, j])
            variances = []
            for x in np.flatnonzero(self._tag_robot != r).tolist():
                ja = column.get(pair_key(nodes[mine[i]], nodes[x]))
                jb = column.get(pair_key(nodes[mine[j]], nodes[x]))
                bias = (
                    0.0 if ja is None or jb is None else cov[ja, ja] + cov[jb, jb] - 2 * cov[ja, jb]
                )
                variances.append(2.0 * noise**2 + bias)
            if span > 0.0 and variances:
                out[r] = min(math.sqrt(float(np.median(variances))) / span, math.pi)
        return out

    # ---------------------------------------------------------------- measurements
    @property
    def _names(self) -> tuple[str, ...]:
        return self.layout.robots

    def _tag_ranges(self, events: list[RangeEvent], at: float, *, prior_bias: bool) -> TagRanges:
        """One range per tag pair of ``events`` (their median, :meth:`RangeBatch.build`), the
        fixed bias removed; an online bias as the window's key, or with ``prior_bias`` its
        prior mean removed (the start's shape). Each tag's arm is where the tag was at the
        median measurement time (stamp minus ``uwb.range_delay``) of its pair's ranges in the
        robot's body frame at ``at`` (moved by the
        odometry between the two times), so that a step's key at ``at`` explains ranges
        taken before it."""
        models = [b for b in RangeBatch.build(events, self._context) if isinstance(b, RangeBatch)]
        delay = self.config.uwb.range_delay  # the geometry a range measures is that much older
        times: dict[tuple[str, str], list[float]] = {}
        for m in events:
            na, nb = self.config.range_nodes(m)
            times.setdefault((min(na, nb), max(na, nb)), []).append(m.t - delay)
        rows: list[tuple[int, int, float, float, int, float]] = []
        names = self._names
        for b in models:
            cols = b.bias_columns if b.bias_columns is not None else np.full(len(b), -1)
            for k in range(len(b)):
                na, nb = b.nodes[k]
                ta = self._tag_of.get(na, self._first_tag[names[int(b.index_a[k])]])
                tb = self._tag_of.get(nb, self._first_tag[names[int(b.index_b[k])]])
                j = self._bias_of_column.get(int(cols[k]), -1)
                z = float(b.distance[k] - b.bias[k])
                if prior_bias and j >= 0:
                    z -= float(self._prior.marginal_mean[j])
                    j = -1
                stamps = times[(min(na, nb), max(na, nb))]
                sigma = float(b.sigma[k])
                rows.append((ta, tb, max(z, 0.0), sigma, j, float(np.median(stamps))))
        tag_a = np.array([r[0] for r in rows], dtype=np.intp)
        tag_b = np.array([r[1] for r in rows], dtype=np.intp)
        when_a = np.array([r[5] for r in rows], float)
        return TagRanges(
            tag_a,
            tag_b,
            self._tag_robot[tag_a],
            self._tag_robot[tag_b],
            self._moved_arms(tag_a, when_a, at),
            self._moved_arms(tag_b, when_a, at),
            np.array([r[2] for r in rows], float),
            np.array([r[3] for r in rows], float),
            np.array([r[4] for r in rows], dtype=np.intp),
        )

    def _moved_arms(self, tags: NDArray[np.intp], when: FloatArray, at: float) -> FloatArray:
        """Each tag's lever arm moved to where its robot's odometry had it at ``when`` in its
        body frame at ``at`` (the arm itself where the robot has no odometry then)."""
        arms = self._arms[tags].copy()
        for k, (tag, t) in enumerate(zip(tags.tolist(), when.tolist(), strict=True)):
            robot = self._names[int(self._tag_robot[tag])]
            now, then = self._odometry(robot, at), self._odometry(robot, t)
            if math.isnan(now[0]) or math.isnan(then[0]) or t == at:
                continue
            moved = pose_of(np.array(now)).between(pose_of(np.array(then)))
            arms[k] = moved.transformFrom(arms[k])
        return arms

    def _height_at(self, robot: str, lo: float, hi: float) -> float:
        """The median height of ``robot`` measured in ``(lo, hi]`` (NaN: none)."""
        values = [z for t, z, _ in self._heights[robot] if lo < t <= hi]
        return float(np.median(values)) if values else math.nan

    def _step_heights(self, lo: float, hi: float) -> dict[int, tuple[float, float]]:
        """Per robot with heights in ``(lo, hi]``: their median and its std (at least
        ``HEIGHT_FLOOR``); older ones dropped."""
        out: dict[int, tuple[float, float]] = {}
        for i, robot in enumerate(self._names):
            queue = self._heights[robot]
            taken = [(z, s) for t, z, s in queue if lo < t <= hi]
            while queue and queue[0][0] <= hi:
                queue.popleft()
            if taken:  # a range finder's noise is white: the median of n has std ~ s / sqrt(n)
                z = float(np.median([z for z, _ in taken]))
                s = float(np.median([s for _, s in taken])) / math.sqrt(len(taken))
                out[i] = (z, max(HEIGHT_FLOOR, s))
        return out

    def _odometry(self, robot: str, t: float) -> tuple[float, float, float, float]:
        """``robot``'s odometry pose ``(x, y, z, yaw)`` in its own frame at ``t`` (NaN: none)."""
        x, y, yaw = self.odometry.pose(robot, t)
        times, values = self._odom_z[robot]
        if math.isnan(x) or not times:
            return (math.nan,) * 4
        z = float(np.interp(t, times, values))
        return (x, y, z, yaw)

    def _walk(self, dt: float) -> Motion:
        """Every robot's random walk over ``dt`` (no odometry)."""
        n = len(self._names)
        step = [UNKNOWN_SPEED * dt] * 3 + [UNKNOWN_TURN_RATE * dt]
        sigma = np.maximum(np.tile(step, (n, 1)), ODOMETRY_FLOOR)
        return Motion(np.zeros((n, 4)), sigma, np.zeros(n, bool), dt)

    def _motion(self, t: float) -> Motion:
        """Every robot's displacement in its body frame and turn since the last step, and
        their stds (module docstring)."""
        dt = max(t - self.t, 0.0)
        random = self._walk(dt)
        delta, sigma, measured = random.delta, random.sigma.copy(), random.measured.copy()
        for i, robot in enumerate(self._names):
            now = self._odometry(robot, t)
            before = self._anchor.get(robot, (math.nan,) * 4)
            self._anchor[robot] = now
            if math.isnan(now[0]) or math.isnan(before[0]):
                continue
            c, s = math.cos(before[3]), math.sin(before[3])
            dx, dy, dz = now[0] - before[0], now[1] - before[1], now[2] - before[2]
            turn = float(wrap_angle(now[3] - before[3]))
            delta[i] = (c * dx + s * dy, -s * dx + c * dy, dz, turn)
            moved = math.sqrt(dx * dx + dy * dy + dz * dz)
            walk = ODOMETRY_WALK**2 * dt + ODOMETRY_FLOOR**2
            sigma[i, :3] = math.sqrt((ODOMETRY_RELATIVE * moved) ** 2 + walk)
            sigma[i, 3] = math.sqrt(
                (TURN_RELATIVE * abs(turn)) ** 2 + YAW_WALK**2 * dt + TURN_FLOOR**2
            )
            measured[i] = True
            self._moved_each[i] += moved
            if i != self._ref:
                self._moved += moved
        return Motion(delta, sigma, measured, dt)

    # ---------------------------------------------------------------- the estimate
    def _best(self, t: float) -> PoseWindow:
        """The hypothesis to publish: while several are kept, the one whose graph fits the
        measurements best (least cost), chosen again every ``CHOOSE_PERIOD``."""
        if len(self.hypotheses) == 1:
            return self.hypotheses[0]
        if self._published is not None:
            window, chosen = self._published
            if any(h is window for h in self.hypotheses) and t - chosen < CHOOSE_PERIOD:
                return window
        best = min(self.hypotheses, key=lambda h: h.cost())
        self._published = (best, t)
        return best

    def _estimate(self, t: float) -> Estimate:
        best = self._best(t)
        rel, cov, yaw_var = best.relative()
        others = self.layout.others
        positions = {r: position_of(rel[k, :3]) for k, r in enumerate(others)}
        covariances = {r: covariance_of(cov[k]) for k, r in enumerate(others)}
        yaws = {
            r: (float(rel[k, 3]), math.sqrt(max(float(yaw_var[k]), 0.0)))
            for k, r in enumerate(others)
        }
        biases = {
            pair: (float(m), float(sd))
            for pair, m, sd in zip(
                self.layout.bias_pairs, best.biases.tolist(), best.bias_std().tolist(), strict=True
            )
        }
        observable = self._observable
        est = Estimate(
            t,
            self.method,
            self.layout.reference,
            positions,
            covariances,
            biases=biases,
            orientation_observable=observable,
            n_modes=len(self.hypotheses),
            particles=len(self.hypotheses),
            frame=BODY_FRAME,
            yaws=yaws,
            shape={} if observable else dict(positions),
            shape_covariances={} if observable else dict(covariances),
            shape_gauge="" if observable else OWN_FRAME,
        )
        self.last_estimate = est
        if self.keeps_run:
            if self.publishes(t):
                self._unsmoothed.append((best.step, est))
            self._smooth(t - SMOOTH_DELAY)
        return est

    # ---------------------------------------------------------------- the smoothed run
    def smoothed_estimates(self) -> list[Estimate]:
        """The run smoothed at a fixed lag: each published step's poses as the window
        estimated them ``SMOOTH_DELAY`` later (the run's last steps: at its end), the rest of
        the causal estimate kept (covariances too: not narrowed; biases, flags). ``[]`` where
        the run was not kept (:attr:`keeps_run`)."""
        if not self.keeps_run:
            return []
        self._smooth(math.inf)
        return list(self._smoothed)

    def _smooth(self, until: float) -> None:
        """Smooth the published steps up to ``until`` with what the best window estimates of
        them now (every hypothesis steps in lockstep); a step it no longer holds keeps its
        causal poses."""
        best = self._best(self.t) if self.hypotheses else None
        while self._unsmoothed and self._unsmoothed[0][1].t <= until:
            step, causal = self._unsmoothed.popleft()
            rel = None if best is None else best.relative_at(step)
            if rel is None:
                self._smoothed.append(causal)
                continue
            others = self.layout.others
            positions = {r: position_of(rel[k, :3]) for k, r in enumerate(others)}
            yaws = {r: (float(rel[k, 3]), causal.yaws[r][1]) for k, r in enumerate(others)}
            shape = {} if causal.orientation_observable else dict(positions)
            self._smoothed.append(
                dataclasses.replace(causal, positions=positions, yaws=yaws, shape=shape)
            )
