"""Fault injection: transforms of an event stream that reproduce what goes wrong on a real team.

A fault is a function of the event stream, not of a source, so the same faults serve the
simulator, a bag run and a live replay alike (the commands apply :func:`inject` to whatever
their source yields; ``relloc serve`` applies a :class:`FaultInjector` to every event it
receives; ``relloc replay`` applies one to the messages it publishes,
:mod:`relloc.live.message_faults`). Every fault is seeded and deterministic; a stream with
no fault passes through unchanged.

* ``drop``: each measurement (odometry, range, detection) is lost with a probability;
* ``silence``: one robot sends nothing in a time window (its odometry, its ranges, its
  detections);
* ``range_burst``: every range in a window reads ``offset`` metres long (a multipath burst, a
  transceiver glitch);
* ``odom_reset``: from a time on, one robot's odometry restarts at (0, 0, 0) (a driver
  restart); ``odom_jump``: its odometry position steps by a vector (a corrupted integrator);
* ``kidnap``: from a time on, one robot is displaced by a vector that its odometry never sees
  (picked up and put down): its ground truth moves, and every range to it changes by the
  geometry of the displacement, computed from the latest ground truth of both robots (so the
  stream must carry ground truth, as the simulator and mocap recordings do);
* ``stamp_shift``: the ``n``-th message (of any kind) gets its stamp shifted by ``dt``
  seconds (one clock glitch); ``stream_jump``: every stamp from a time on is shifted (a
  clock step of the whole team).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from relloc.events import DetectionEvent, Event, GroundTruthEvent, OdometryEvent, RangeEvent


@dataclass(frozen=True)
class Window:
    """A robot (or ``""``: every robot) and a time window ``[start, end)`` of stream time."""

    start: float
    end: float
    robot: str = ""

    def covers(self, t: float) -> bool:
        return self.start <= t < self.end


@dataclass(frozen=True)
class Faults:
    """The faults to inject (module docstring); the default injects none."""

    drop: float = 0.0
    """Probability of losing each measurement."""
    silence: tuple[Window, ...] = ()
    range_burst: tuple[tuple[Window, float], ...] = ()
    """(window, offset in m) added to every range in the window."""
    odom_reset: tuple[tuple[str, float], ...] = ()
    """(robot, time): odometry restarts at the origin then."""
    odom_jump: tuple[tuple[str, float, float, float], ...] = ()
    """(robot, time, dx, dy): odometry position steps by (dx, dy) then."""
    kidnap: tuple[tuple[str, float, float, float], ...] = ()
    """(robot, time, dx, dy): the robot is displaced by (dx, dy) then, unseen by odometry."""
    stamp_shift: tuple[tuple[int, float], ...] = ()
    """(index, dt): the index-th event's stamp shifted by dt seconds."""
    stream_jump: tuple[tuple[float, float], ...] = ()
    """(time, dt): every stamp from that time on shifted by dt seconds."""
    seed: int = 0

    @property
    def active(self) -> bool:
        return self != Faults(seed=self.seed)


@dataclass
class _State:
    """What a running injection remembers: odometry offsets at resets and jumps, and the
    latest ground truth of every robot (for kidnapped ranges)."""

    rng: np.random.Generator
    odom_origin: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    odom_offset: dict[str, tuple[float, float]] = field(default_factory=dict)
    truth: dict[str, tuple[float, float]] = field(default_factory=dict)


class FaultInjector:
    """The faults applied one event at a time, for a stream that is not an iterable (the live
    server's arrivals): ``injector(event)`` is the event as faulted, or ``None`` if lost. The
    counters say what was done (``dropped``, ``silenced``, ``shifted``, ...)."""

    def __init__(self, faults: Faults) -> None:
        self.faults = faults
        self.state = _State(np.random.default_rng(faults.seed))
        self.index = 0
        self.counts: dict[str, int] = {}
        self._shifts = dict(faults.stamp_shift)

    def __call__(self, ev: Event) -> Event | None:
        f = self.faults
        index, self.index = self.index, self.index + 1
        out = _transform(ev, f, self.state, self.counts)
        if out is None:
            return None
        dt = self._shifts.get(index, 0.0) + sum(d for t0, d in f.stream_jump if ev.t >= t0)
        if dt:
            self.counts["shifted"] = self.counts.get("shifted", 0) + 1
            return dataclasses.replace(out, t=out.t + dt)
        return out


def inject(events: Iterable[Event], faults: Faults) -> Iterator[Event]:
    """``events`` with ``faults`` applied (times are the original stream's)."""
    if not faults.active:
        yield from events
        return
    injector = FaultInjector(faults)
    for ev in events:
        out = injector(ev)
        if out is not None:
            yield out


def _robots(ev: Event) -> tuple[str, ...]:
    if isinstance(ev, RangeEvent):
        return (ev.robot_a, ev.robot_b)
    return (getattr(ev, "robot", ""),)


def _transform(ev: Event, f: Faults, s: _State, counts: dict[str, int]) -> Event | None:
    if isinstance(ev, GroundTruthEvent):
        dx, dy = _kidnap_offset(f, ev.robot, ev.t)
        x, y, *rest = ev.position
        s.truth[ev.robot] = (x, y)  # the untouched truth: ranges are corrected from it
        return dataclasses.replace(ev, position=(x + dx, y + dy, *rest)) if dx or dy else ev
    if isinstance(ev, OdometryEvent | RangeEvent | DetectionEvent):
        if f.drop > 0.0 and s.rng.random() < f.drop:
            counts["dropped"] = counts.get("dropped", 0) + 1
            return None
        robots = _robots(ev)
        if any(w.covers(ev.t) and (not w.robot or w.robot in robots) for w in f.silence):
            counts["silenced"] = counts.get("silenced", 0) + 1
            return None
    if isinstance(ev, RangeEvent):
        d = ev.distance + sum(off for w, off in f.range_burst if w.covers(ev.t))
        d += _kidnapped_range_change(f, s, ev)
        return dataclasses.replace(ev, distance=d) if d != ev.distance else ev
    if isinstance(ev, OdometryEvent):
        return _odometry(ev, f, s)
    return ev


def _odometry(ev: OdometryEvent, f: Faults, s: _State) -> OdometryEvent:
    x, y, yaw = ev.x, ev.y, ev.yaw
    resets = [t for r, t in f.odom_reset if r == ev.robot and ev.t >= t]
    if resets:
        origin = s.odom_origin.setdefault(ev.robot, (x, y, yaw))
        # The new odometry frame is the pose at the reset: express the pose in it.
        c, sn = math.cos(origin[2]), math.sin(origin[2])
        ex, ey = x - origin[0], y - origin[1]
        x, y, yaw = c * ex + sn * ey, -sn * ex + c * ey, math.remainder(yaw - origin[2], math.tau)
    for r, t, dx, dy in f.odom_jump:
        if r == ev.robot and ev.t >= t:
            x, y = x + dx, y + dy
    if (x, y, yaw) == (ev.x, ev.y, ev.yaw):
        return ev
    return dataclasses.replace(ev, x=x, y=y, yaw=yaw)


def _kidnap_offset(f: Faults, robot: str, t: float) -> tuple[float, float]:
    dx = sum(k[2] for k in f.kidnap if k[0] == robot and t >= k[1])
    dy = sum(k[3] for k in f.kidnap if k[0] == robot and t >= k[1])
    return dx, dy


def _kidnapped_range_change(f: Faults, s: _State, ev: RangeEvent) -> float:
    """How much the kidnapping changed the true distance of ``ev``'s pair (0 without one)."""
    a, b = s.truth.get(ev.robot_a), s.truth.get(ev.robot_b)
    oa, ob = _kidnap_offset(f, ev.robot_a, ev.t), _kidnap_offset(f, ev.robot_b, ev.t)
    if a is None or b is None or (oa == (0.0, 0.0) and ob == (0.0, 0.0)):
        return 0.0
    before = math.hypot(a[0] - b[0], a[1] - b[1])
    after = math.hypot(a[0] + oa[0] - b[0] - ob[0], a[1] + oa[1] - b[1] - ob[1])
    return after - before


# ---------------------------------------------------------------- command-line options
def parse(
    *,
    drop: float = 0.0,
    silence: Iterable[str] = (),
    range_burst: Iterable[str] = (),
    odom_reset: Iterable[str] = (),
    odom_jump: Iterable[str] = (),
    kidnap: Iterable[str] = (),
    stamp_shift: Iterable[str] = (),
    stream_jump: Iterable[str] = (),
    seed: int = 0,
) -> Faults:
    """:class:`Faults` from the commands' option strings: ``--silence ROBOT:START:END``,
    ``--range-burst START:END:OFFSET``, ``--odom-reset ROBOT:T``, ``--odom-jump ROBOT:T:DX:DY``,
    ``--kidnap ROBOT:T:DX:DY``, ``--stamp-shift INDEX:DT``, ``--stream-jump T:DT``. A malformed
    value is a :class:`ValueError` naming it."""
    if not 0.0 <= drop < 1.0:
        raise ValueError(f"--drop must be in [0, 1), got {drop}")

    def fields_of(text: str, n: int, option: str) -> list[str]:
        parts = text.split(":")
        if len(parts) != n:
            raise ValueError(f"--{option} {text!r}: expected {n} fields separated by ':'")
        return parts

    def num(text: str, option: str) -> float:
        try:
            return float(text)
        except ValueError:
            raise ValueError(f"--{option}: {text!r} is not a number") from None

    sil = []
    for text in silence:
        r, a, b = fields_of(text, 3, "silence")
        sil.append(Window(num(a, "silence"), num(b, "silence"), r))
    bursts = []
    for text in range_burst:
        start, end, off = (num(p, "range-burst") for p in fields_of(text, 3, "range-burst"))
        bursts.append((Window(start, end), off))
    resets = []
    for text in odom_reset:
        r, t = fields_of(text, 2, "odom-reset")
        resets.append((r, num(t, "odom-reset")))

    def moves(values: Iterable[str], option: str) -> tuple[tuple[str, float, float, float], ...]:
        out = []
        for text in values:
            r, *rest = fields_of(text, 4, option)
            t, dx, dy = (num(p, option) for p in rest)
            out.append((r, t, dx, dy))
        return tuple(out)

    shifts = []
    for text in stamp_shift:
        i, dt = fields_of(text, 2, "stamp-shift")
        shifts.append((int(num(i, "stamp-shift")), num(dt, "stamp-shift")))
    jumps = []
    for text in stream_jump:
        at, by = (num(p, "stream-jump") for p in fields_of(text, 2, "stream-jump"))
        jumps.append((at, by))
    return Faults(
        drop=drop,
        silence=tuple(sil),
        range_burst=tuple(bursts),
        odom_reset=tuple(resets),
        odom_jump=moves(odom_jump, "odom-jump"),
        kidnap=moves(kidnap, "kidnap"),
        stamp_shift=tuple(shifts),
        stream_jump=tuple(jumps),
        seed=seed,
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The fault-injection options of the commands that run a stream (``relloc demo``,
    ``relloc run``, ``relloc serve``) or publish one (``relloc replay``: the messages are
    faulted before they go out); times are the stream's (s: header stamps)."""
    g = parser.add_argument_group("fault injection (for testing robustness)")
    g.add_argument(
        "--drop",
        type=float,
        default=0.0,
        metavar="P",
        help="lose each measurement with probability P",
    )
    g.add_argument(
        "--silence",
        action="append",
        default=[],
        metavar="ROBOT:START:END",
        help="a robot sends nothing then",
    )
    g.add_argument(
        "--range-burst",
        action="append",
        default=[],
        metavar="START:END:OFFSET",
        help="every range reads OFFSET m long then",
    )
    g.add_argument(
        "--odom-reset",
        action="append",
        default=[],
        metavar="ROBOT:T",
        help="the robot's odometry restarts at the origin at T",
    )
    g.add_argument(
        "--odom-jump",
        action="append",
        default=[],
        metavar="ROBOT:T:DX:DY",
        help="the robot's odometry steps by (DX, DY) at T",
    )
    g.add_argument(
        "--kidnap",
        action="append",
        default=[],
        metavar="ROBOT:T:DX:DY",
        help="the robot is moved by (DX, DY) at T, unseen by its odometry",
    )
    g.add_argument(
        "--stamp-shift",
        action="append",
        default=[],
        metavar="INDEX:DT",
        help="the INDEX-th event's stamp is shifted by DT s",
    )
    g.add_argument(
        "--stream-jump",
        action="append",
        default=[],
        metavar="T:DT",
        help="every stamp from T on is shifted by DT s (a clock step)",
    )
    g.add_argument("--fault-seed", type=int, default=0, metavar="N", help="seed of --drop")


def from_args(args: argparse.Namespace) -> Faults:
    """The :class:`Faults` of :func:`add_arguments`' options (a :class:`ValueError` names a
    malformed one)."""
    return parse(
        drop=args.drop,
        silence=args.silence,
        range_burst=args.range_burst,
        odom_reset=args.odom_reset,
        odom_jump=args.odom_jump,
        kidnap=args.kidnap,
        stamp_shift=args.stamp_shift,
        stream_jump=args.stream_jump,
        seed=args.fault_seed,
    )
