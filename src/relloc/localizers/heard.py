"""When each robot was last heard of: the unseen-robot widening and the orientation kernel's pause.

Every fused measurement is news of some robots (``MeasurementModel.heard``: a range of its
pair, a sighting or a relative observation of its observer and target), and a range's count
as ranged (``MeasurementModel.ranged``). From those times:

* a robot is **unseen** once its odometry is older than the extrapolation horizon and it has
  had no measurement for ``_UNRANGED_AFTER``: from the later of the two, nothing says where it
  went. The filter holds it where it was last seen (spreading its hypotheses would thin out
  the whole formation's); the published covariances grow instead by what it may have driven
  meanwhile, at ``unseen_speed`` in an unknown direction (:attr:`Estimate.unseen`); a robot
  still measured while its odometry is past the horizon moves at ``unseen_speed`` in the
  filter, its measurements holding it (:meth:`Heard.moving_unknown`), and moves on from where
  they took it when its odometry comes back, if they fixed its position (:meth:`Heard.resume`);
* the formation is **split** while some robot has had no range for ``_UNRANGED_AFTER``, and
  as long again after every robot is ranged once more (the orientations are then still the
  split's mixture): a filter's orientation kernel treats the orientation as a static
  parameter of one rigid formation, and a robot out of ranging splits it into parts whose
  relative orientation nothing observes (docs/howto/faults.md).
"""

from __future__ import annotations

import math
from typing import Any

from relloc.config import TeamConfig
from relloc.estimate import Covariance
from relloc.events import RangeEvent, RelativeObservation, SightingEvent
from relloc.filter.measurement import hook
from relloc.filter.registry import model_for
from relloc.filter.state import TeamLayout
from relloc.odometry import MAX_EXTRAPOLATION, OdometryTrack

_UNRANGED_AFTER = 2.0
"""Seconds without a range after which a robot pauses the orientation kernel (and, without
any measurement, may be unseen)."""

Covariances = dict[str, Covariance]


class Heard:
    """Each robot's newest measurement and newest range (module docstring)."""

    def __init__(self, config: TeamConfig, layout: TeamLayout) -> None:
        self.robots, self.reference = layout.robots, layout.reference
        self.unseen_speed, self.horizon = config.filter.odometry.unseen_speed, MAX_EXTRAPOLATION
        self.ranged: dict[str, float] = {}
        """Each robot's newest range (counted from the start's end)."""
        self.measured: dict[str, float] = {}
        """Each robot's newest measurement of any kind."""
        self.split_at = -math.inf
        """When some robot was last out of ranging."""
        self.carried: dict[str, tuple[float, dict[str, int]]] = {}
        """Per robot its measurements move while its odometry is silent (:meth:`carry`): its
        odometry's last stamp before the silence, and per teammate that measured it since, the
        most dimensions of its position one measurement gave (a range 1, a range and bearing
        or a relative position 2)."""

    def note(self, batch: list[Any], *, ranged: bool = True) -> None:
        """The robots ``batch`` is news of; with ``ranged``, its ranges count for the kernel
        (not the start's: the kernel's clock starts at its end)."""
        for m in batch:
            model = model_for(m)
            if model is None:
                continue
            robots = hook(model, "heard")(m)
            if not robots:
                continue
            if ranged and hook(model, "ranged"):
                for r in robots:
                    self.ranged[r] = m.t
            for r in robots:
                self.measured[r] = max(self.measured.get(r, -math.inf), m.t)
                carried = self.carried.get(r)
                if carried is not None:
                    for other in robots:
                        if other != r:
                            carried[1][other] = max(carried[1].get(other, 0), _dimensions(m))

    def unseen(self, t: float, tracks: dict[str, OdometryTrack]) -> dict[str, float]:
        """The robots unseen at ``t`` with the seconds their motion has been unknown; robots
        never heard at all are left to the filter's own prior. None without ``unseen_speed``."""
        if not self.unseen_speed:
            return {}
        out = {}
        for robot in self.robots:
            track = tracks[robot]
            measured = self.measured.get(robot, -math.inf)
            if track.empty and measured == -math.inf:
                continue
            odom = track.last_time + self.horizon
            if t - measured > _UNRANGED_AFTER and t > odom:
                out[robot] = round(t - max(odom, measured), 3)
        return out

    def moving_unknown(self, robot: str, t: float, track: OdometryTrack) -> bool:
        """Whether ``robot`` is measured after its odometry went past the horizon, and within
        ``_UNRANGED_AFTER`` of ``t``: it is there, its motion is not told (its odometry's link
        dropped, say), so the filter lets it move at ``unseen_speed``, its measurements holding
        it. A robot nothing measures since is held instead (module docstring)."""
        ended = track.last_time + self.horizon
        if track.empty or t <= ended:
            return False
        measured = self.measured.get(robot, -math.inf)
        return measured > ended and t - measured <= _UNRANGED_AFTER

    def carry(self, robot: str, silent_from: float) -> None:
        """``robot``'s measurements move it from now on (:meth:`moving_unknown`), its odometry
        silent since ``silent_from``: what measures it meanwhile is kept for :meth:`resume`."""
        self.carried.setdefault(robot, (silent_from, {}))

    def resume(self, robot: str, back: float) -> bool:
        """``robot``'s odometry is back (its first message after the silence stamped ``back``):
        whether its measurements followed it through the silence, so that the filter has it
        where they took it and its odometry's displacement over the silence would move it
        twice. They did over a silence longer than ``_UNRANGED_AFTER`` if they fixed its
        position (two teammates' ranges or bearings, or one's range and bearing); a single
        range leaves it anywhere on a circle, and over a shorter silence they cannot have moved
        it far: the displacement is the better account of where it went then."""
        silent_from, fixes = self.carried.pop(robot)
        return back - silent_from > _UNRANGED_AFTER and sum(fixes.values()) >= 2

    def widen(self, covs: Covariances, unseen: dict[str, float]) -> Covariances:
        """The covariances grown for what the unseen robots may have driven: ``(speed *
        seconds)^2`` per axis; a relative position is unknown by its own robot's motion and
        by the reference's."""
        speed = self.unseen_speed
        ref = unseen.get(self.reference, 0.0)
        out = dict(covs)
        for robot, cov in covs.items():
            add = (speed * unseen.get(robot, 0.0)) ** 2 + (speed * ref) ** 2
            if add:
                out[robot] = tuple(
                    tuple(v + add if i == j else v for j, v in enumerate(row))
                    for i, row in enumerate(cov)
                )
        return out

    def split(self, t: float) -> bool:
        """Whether the formation is split at ``t`` (module docstring)."""
        if any(t - self.ranged.get(r, t) > _UNRANGED_AFTER for r in self.robots):
            self.split_at = t
        return t - self.split_at < _UNRANGED_AFTER

    def shift_time(self, dt: float) -> None:
        self.ranged = {r: tr + dt for r, tr in self.ranged.items()}
        self.measured = {r: tr + dt for r, tr in self.measured.items()}
        self.split_at += dt
        if dt < 0:  # odometry stamps move back with the clock (OdometryTracks.follow)
            self.carried = {r: (t + dt, fixes) for r, (t, fixes) in self.carried.items()}


def _dimensions(m: Any) -> int:
    """How many dimensions of a teammate's position one measurement gives: a range or a
    bearing 1, both or a relative position 2."""
    if isinstance(m, RangeEvent):
        return 1
    if isinstance(m, SightingEvent):
        return (m.range is not None) + (m.bearing is not None)
    return 2 if isinstance(m, RelativeObservation) else 0
