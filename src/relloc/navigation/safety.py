"""When a robot navigating on the relative estimate must not move, and why.

The derivation: docs/explanation/internals.md, section ``relloc.navigation.safety``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields
from typing import Any

from relloc.config import ConfigError, with_numeric_overrides
from relloc.estimate import DOMINANT_MODE_WEIGHT, Estimate

__all__ = ["SafetyConfig", "SafetyGate", "StopRecord"]

log = logging.getLogger("relloc.navigation")

TERMINAL = ("interrupted", "goal reached")


@dataclass(frozen=True)
class SafetyConfig:
    """Bounds of the safety gate."""

    max_age: float = 0.6
    """Estimates and odometry older than this are stale (s); estimates come at 10 Hz."""
    max_std: float = 0.2
    """Largest acceptable position standard deviation of the estimate (m)."""
    start_std: float = 0.15
    """Largest std at which a held robot (re)starts (m): below ``max_std``, so an estimate that
    just passes the stop bound, and may still be off by twice that, does not start the robot."""
    settle_time: float = 2.0
    """Every check must pass this long in a row before the robot (re)starts (s)."""
    min_mode_weight: float = DOMINANT_MODE_WEIGHT
    """Smallest posterior weight of the published mode (the rest competes with it)."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
                raise ConfigError(f"safety.{f.name}: expected a number >= 0, got {value!r}")
        if self.max_age == 0 or self.max_std == 0 or self.start_std == 0:
            raise ConfigError("safety: max_age, max_std and start_std must be positive")

    def updated(self, overrides: dict[str, Any], where: str = "safety") -> SafetyConfig:
        """A copy with the keys of ``overrides`` changed (unknown keys are errors)."""
        return with_numeric_overrides(self, overrides, where)


@dataclass(frozen=True)
class StopRecord:
    """One transition of the gate: the robot was held (``stopped=True``) or released."""

    t: float
    reason: str
    detail: str
    stopped: bool


class SafetyGate:
    """Checks estimate age, estimate std and odometry age; keeps the start/hold state."""

    def __init__(self, config: SafetyConfig | None = None, robot: str = "") -> None:
        self.config = config or SafetyConfig()
        self.robot = robot
        self.records: list[StopRecord] = []
        self.reason: str | None = "no_estimate"
        """Why the robot is held now (``None`` while it may move)."""
        self.untrusted: str | None = None
        """Why the latest estimate cannot be trusted (set by the live layer), else ``None``."""
        self._ok_since: float | None = None
        self._terminal: str | None = None
        self._ever_released = False

    # ---------------------------------------------------------------- checks
    def check(
        self, now: float, estimate: Estimate | None, odometry_time: float | None
    ) -> tuple[str, str] | None:
        """The first failed check as ``(reason, detail)``, or ``None`` if all pass now."""
        cfg = self.config
        robot = self.robot
        if self.untrusted is not None:
            return "unverified", self.untrusted
        if estimate is None or robot not in estimate.positions:
            return "no_estimate", f"no estimate of {robot} yet"
        if estimate.recovering:
            return "recovering", "the localizer found itself lost and is recovering"
        if estimate.inconsistent:
            return "inconsistent", "the estimate's covariance no longer covers its innovations"
        age = now - estimate.t
        if age > cfg.max_age:
            return "stale_estimate", f"estimate is {age:.2f} s old (max {cfg.max_age:g} s)"
        unseen = {r: s for r, s in estimate.unseen.items() if r in (robot, estimate.reference)}
        if unseen:
            return "unseen", ", ".join(
                f"{r} unheard for {s:.1f} s" for r, s in sorted(unseen.items())
            )
        if not estimate.orientation_observable:
            return "unobservable", estimate.status
        if estimate.mode_weight < cfg.min_mode_weight:
            return "modes", f"{estimate.status} (min {cfg.min_mode_weight:g})"
        std = estimate.std(robot)
        bound = cfg.max_std if self.reason is None else min(cfg.start_std, cfg.max_std)
        if not math.isfinite(std) or std > bound:
            return "uncertain", f"estimate std {std:.3f} m > {bound:g} m"
        if odometry_time is None:
            return "no_odometry", f"no odometry of {robot} yet"
        odom_age = now - odometry_time
        if odom_age > cfg.max_age:
            return "stale_odometry", f"odometry is {odom_age:.2f} s old (max {cfg.max_age:g} s)"
        return None

    def evaluate(
        self, now: float, estimate: Estimate | None, odometry_time: float | None
    ) -> str | None:
        """Run the checks at ``now``; the reason to hold the robot, or ``None`` to let it move.

        Records and logs every transition; once :meth:`stop_for_good` was called, always
        returns that terminal reason.
        """
        if self._terminal is not None:
            return self._terminal
        failed = self.check(now, estimate, odometry_time)
        if failed is not None:
            self._ok_since = None
            self._hold(now, *failed)
            return self.reason
        if self._ok_since is None:
            self._ok_since = now
        if self.reason is not None and now - self._ok_since >= self.config.settle_time - 1e-9:
            what = "converged, starting" if not self._ever_released else "resuming"
            std = estimate.std(self.robot) if estimate is not None else math.nan
            self._record(now, "released", f"{what} (estimate std {std:.3f} m)", stopped=False)
            self.reason = None
            self._ever_released = True
        return self.reason

    def stop_for_good(self, now: float, reason: str, detail: str = "") -> None:
        """A terminal stop (Ctrl-C, end of the path): the robot is held from now on."""
        if self._terminal is not None:
            return
        self._terminal = reason
        self.reason = reason
        self._record(now, reason, detail or reason, stopped=True)

    @property
    def terminal(self) -> str | None:
        return self._terminal

    # ---------------------------------------------------------------- records
    def _hold(self, now: float, reason: str, detail: str) -> None:
        if self.reason == reason:
            return
        # Before the first release the robot is simply waiting; record only reason changes.
        self.reason = reason
        self._record(now, reason, detail, stopped=True)

    def _record(self, now: float, reason: str, detail: str, *, stopped: bool) -> None:
        self.records.append(StopRecord(now, reason, detail, stopped))
        level = logging.INFO if not stopped or reason == "goal reached" else logging.WARNING
        verb = "stop" if stopped else "go"
        log.log(level, "%s %s at t=%.2f: %s (%s)", verb, self.robot, now, reason, detail)
