"""Learned UWB range correction (``PF_UL``): a stage between the source and the localizer.

The derivation: docs/explanation/internals.md, section ``relloc.stages.range_correction``.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.events import Event, OdometryEvent, RangeEvent
from relloc.odometry import OdometryTrack
from relloc.ranging.inference import OFFSET_MODES, ModelSet, PairModel
from relloc.stages.correction_check import CorrectionCheck

YawProvider = Callable[[str, float], float | None]
"""``(robot, t) -> heading in the shared frame (rad)``, or ``None`` if unknown."""

OUTCOMES: tuple[str, ...] = (
    "corrected",
    "fallback",
    "corrected_repeat",
    "window_not_full",
    "no_model",
    "no_yaw",
    "stale_yaw",
    "invalid_range",
    "out_of_order",
    "already_corrected",
    "out_of_support",
    "checked_off",
)
"""Keys of :attr:`RangeCorrector.stats` that count ranges (each range counts once)."""


@dataclass
class _PairState:
    """Live window of one pair: frames ``[range, yaw_a, yaw_b]``, oldest first."""

    frames: deque[tuple[float, float, float]]
    last_t: float = -math.inf
    last_distance: float = math.nan
    last_error: tuple[float, float] | None = None
    """``(residual, sigma)`` of the current window, reused for repeats; ``None`` until the
    window is full."""


@dataclass
class _ToldYaw:
    t: float
    yaw: float


@dataclass
class RangeCorrector:
    """Correct UWB ranges with per-node-pair models; see the module docstring."""

    models: Mapping[str, PairModel]
    """Pair key -> model (a :class:`~relloc.ranging.inference.ModelSet` or any mapping)."""
    tracks: dict[str, OdometryTrack] = field(default_factory=dict)
    """Per-robot odometry in the shared heading frame; robots not listed get a pose-mode track
    with no heading offset when their first odometry arrives."""
    yaw_provider: YawProvider | None = None
    """If given, headings come from it instead of the stage's own odometry tracks."""
    max_yaw_age: float | None = 1.0
    """Pass a range through if a robot's last heading is older than this (s); None: no limit."""
    max_gap: float | None = 2.0
    """Empty a pair's window when its ranges pause longer than this (s); None: never."""
    offset: str | None = None
    """``manifest`` or ``filter`` (see the module docstring); None: the model directory's
    choice (``ModelSet.offset_mode``), else ``manifest``."""
    self_check: bool = True
    """Judge each pair's correction against the constant on the published estimates and switch
    it off where it hurts (:mod:`relloc.stages.correction_check`)."""
    bias_of: Callable[[str, str], float] | None = None
    """The team's calibrated bias of a node pair (what the filter removes from a range the
    stage passes through), for the self-check; ``None``: zero."""
    stats: Counter[str] = field(default_factory=Counter)
    check: CorrectionCheck = field(default_factory=CorrectionCheck, repr=False)
    _pairs: dict[str, _PairState] = field(default_factory=dict, repr=False)
    _told: dict[str, _ToldYaw] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.offset is None:
            self.offset = str(getattr(self.models, "offset_mode", "manifest"))
        if self.offset not in OFFSET_MODES:
            raise ValueError(f"offset must be one of {OFFSET_MODES}, got {self.offset!r}")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_dir(cls, path: str | Path, **kwargs: object) -> RangeCorrector:
        """Load a model directory written by ``relloc ranging train``."""
        return cls(ModelSet.load(path), **kwargs)  # type: ignore[arg-type]

    @classmethod
    def from_config(
        cls, team: TeamConfig, models: str | Path | Mapping[str, PairModel], **kwargs: object
    ) -> RangeCorrector:
        """Stage for ``team``: odometry tracks with each robot's heading offset, mode, scale."""
        tracks = {
            r.name: OdometryTrack(r.heading_offset, r.odom_scale, r.odom_mode) for r in team.robots
        }
        loaded = ModelSet.load(models) if isinstance(models, str | Path) else models
        kwargs.setdefault("bias_of", lambda a, b: team.uwb.calibration(a, b)[0])
        return cls(loaded, tracks=tracks, **kwargs)  # type: ignore[arg-type]

    # ------------------------------------------------------------------ engine stage
    def process(self, event: Event) -> list[Event]:
        """Engine stage: ranges come out corrected (or passed through), the rest unchanged."""
        if isinstance(event, RangeEvent):
            return [self.correct(event)]
        self.observe(event)
        return [event]

    def feedback(self, estimate: Estimate) -> None:
        """The self-check scores the next ranges with ``estimate``'s positions; a pair it has
        switched is published in the stats (``correction_off.<pair>``: 1 off, 0 back on)."""
        if self.self_check:
            self.check.judge(estimate)

    # ------------------------------------------------------------------ headings
    def observe(self, event: Event) -> None:
        """Feed any event; odometry updates the robot's heading, the rest is ignored."""
        if not isinstance(event, OdometryEvent):
            return
        track = self.tracks.get(event.robot)
        if track is None:
            track = self.tracks[event.robot] = OdometryTrack()
        if event.t > track.last_time:
            track.add(event)

    def set_yaw(self, robot: str, t: float, yaw: float) -> None:
        """Tell the heading of ``robot`` (shared frame, rad) at time ``t``; overrides odometry."""
        self._told[robot] = _ToldYaw(t, yaw)

    def _yaw(self, robot: str, t: float) -> tuple[float | None, bool]:
        """``(heading at t, stale)``; ``(None, False)`` if there is none."""
        if self.yaw_provider is not None:
            yaw = self.yaw_provider(robot, t)
            return (None, False) if yaw is None else (float(yaw), False)
        told = self._told.get(robot)
        if told is not None:
            return told.yaw, self._stale(t - told.t)
        track = self.tracks.get(robot)
        if track is None or track.empty:
            return None, False
        return track.pose_at(t)[2], self._stale(t - track.last_time)

    def _stale(self, age: float) -> bool:
        return self.max_yaw_age is not None and age > self.max_yaw_age

    # ------------------------------------------------------------------ ranges
    def correct(self, event: RangeEvent) -> RangeEvent:
        """The corrected range, or ``event`` itself when it cannot be corrected (counted)."""
        if event.corrected or event.sigma is not None:
            return self._pass(event, "already_corrected")
        if not (math.isfinite(event.distance) and event.distance > 0.0):
            return self._pass(event, "invalid_range")
        key = event.node_pair
        model = self.models.get(key)
        if model is None:
            return self._pass(event, "no_model")
        if model.fallback:
            return self._corrected(event, model, 0.0, float(model.fallback_sigma), "fallback")  # type: ignore[arg-type]
        state = self._pairs.get(key)
        if state is None:
            state = self._pairs[key] = _PairState(deque(maxlen=model.n_steps))
        if event.t < state.last_t:
            return self._pass(event, "out_of_order")
        if self.max_gap is not None and event.t - state.last_t > self.max_gap and state.frames:
            state.frames.clear()
            state.last_error = None
            self.stats["window_reset"] += 1
        if event.distance == state.last_distance and state.frames:
            # The same measurement read again: not a new frame.
            state.last_t = event.t
            if state.last_error is None:
                return self._pass(event, "window_not_full")
            return self._checked(event, model, *state.last_error, "corrected_repeat")
        node_a = event.node_a or event.robot_a
        node_b = event.node_b or event.robot_b
        # Canonical order (as pair_key sorts): yaw_a is the heading of the first node's robot.
        first, second = (
            (event.robot_a, event.robot_b) if node_a <= node_b else (event.robot_b, event.robot_a)
        )
        yaw_a, stale_a = self._yaw(first, event.t)
        yaw_b, stale_b = self._yaw(second, event.t)
        if yaw_a is None or yaw_b is None:
            return self._pass(event, "no_yaw")
        if stale_a or stale_b:
            return self._pass(event, "stale_yaw")
        state.frames.append((event.distance, yaw_a, yaw_b))
        state.last_t = event.t
        state.last_distance = event.distance
        state.last_error = None
        if len(state.frames) < model.n_steps:
            return self._pass(event, "window_not_full")
        window = np.asarray(state.frames, dtype=np.float32)[None]
        raw_residual, raw_sigma = model.predict_raw(window)
        raw, sigma = float(raw_residual[0]), float(raw_sigma[0])
        if not (math.isfinite(raw) and math.isfinite(sigma) and sigma > 0.0):
            state.last_error = None
            return self._pass(event, "model_nonfinite")  # the raw range is better than none
        residual = min(max(raw, model.residual_min), model.residual_max)
        if residual != raw:
            self.stats["clipped"] += 1
        if model.support is not None and not model.support.contains(window)[0]:
            state.last_error = (0.0, self._constant_sigma(model, sigma))
            return self._corrected(event, model, *state.last_error, "out_of_support")
        state.last_error = (residual, sigma)
        return self._checked(event, model, residual, sigma, "corrected")

    @staticmethod
    def _constant_sigma(model: PairModel, sigma: float) -> float:
        """The noise of a range corrected by the pair's constant alone: its validation RMSE."""
        return float(model.fallback_sigma) if model.fallback_sigma else sigma

    def _checked(
        self, event: RangeEvent, model: PairModel, residual: float, sigma: float, reason: str
    ) -> RangeEvent:
        """The self-check's view: both candidates noted (less the pair's constant in either
        offset mode), the constant alone where the pair's correction is switched off."""
        if not self.self_check:
            return self._corrected(event, model, residual, sigma, reason)
        key = event.node_pair
        constant = event.distance - model.offset
        if self.check.note(
            key, event.t, event.robot_a, event.robot_b, constant - residual, constant
        ):
            self.stats[f"correction_off.{key}"] = int(not self.check.enabled(key))
            self.stats["self_check_switched_off"] = self.check.switched_off
            self.stats["self_check_switched_on"] = self.check.switched_on
        if not self.check.enabled(key):
            return self._corrected(
                event, model, 0.0, self._constant_sigma(model, sigma), "checked_off"
            )
        return self._corrected(event, model, residual, sigma, reason)

    def _pass(self, event: RangeEvent, reason: str) -> RangeEvent:
        self.stats[reason] += 1
        bias = 0.0
        if self.bias_of is not None and not event.corrected:
            bias = self.bias_of(event.node_a or event.robot_a, event.node_b or event.robot_b)
        self._used(event, event.distance - bias)
        return event

    def _used(self, event: RangeEvent, distance: float) -> None:
        """Tell the self-check what distance the filter gets for this range (a positive one)."""
        if self.self_check and math.isfinite(distance) and distance > 0.0:
            self.check.used(event.t, event.robot_a, event.robot_b, distance)

    def _corrected(
        self, event: RangeEvent, model: PairModel, residual: float, sigma: float, reason: str
    ) -> RangeEvent:
        """Remove the residual, and the pair's constant in ``manifest`` mode; attach sigma."""
        self.stats[reason] += 1
        if self.offset == "manifest":
            distance, corrected = event.distance - model.offset - residual, True
        else:
            distance, corrected = event.distance - residual, False
        self._used(event, event.distance - model.offset - residual)
        return replace(event, distance=distance, corrected=corrected, sigma=sigma)

    def reset(self) -> None:
        """Forget every window, heading and count (e.g. when a recording restarts)."""
        self._pairs.clear()
        self._told.clear()
        self.check = CorrectionCheck()
        self.tracks = {
            robot: OdometryTrack(
                t.heading_offset,
                t.scale,
                t.mode,
                max_extrapolation=t.max_extrapolation,
                history=t.history,
            )
            for robot, t in self.tracks.items()
        }
        self.stats.clear()
