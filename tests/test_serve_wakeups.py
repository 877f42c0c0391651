"""Waking the live engine only for messages that could make an estimate.

A live server's engine thread woken for each message runs cold, and that was most of its CPU.
``Localizer.wake_rule`` says which events could make the localizer fuse a batch; the Zenoh
source wakes the engine only for those and lets the rest wait in its queue, to be processed
with the next urgent one, in arrival order. These tests check that the rule never lets an
estimate-making event wait (on the simulated team, clean and with faults), that waiting
changes neither the events nor their order, and the source's side of it (tokens, ``rearm``,
bursts kept in arrival order).
"""

from __future__ import annotations

import math
from typing import Any

import pytest

from relloc.config import RobotConfig, TeamConfig
from relloc.events import WAKE_ALWAYS, OdometryEvent, RangeEvent, WakeRule
from relloc.faults import FaultInjector, Faults
from relloc.live import LiveServer, ServeOptions, event_messages, simulated_team
from relloc.localizers.clock import MAX_TIME_JUMP
from relloc.localizers.grid import UPDATE_PERIOD
from relloc.methods import build_pipeline
from relloc.ros.interfaces import encode_sent_time
from relloc.ros.messages import encode, header_stamp_from_cdr, odometry_msg, range_msg
from relloc.sources.zenoh_source import ZenohSource

T0 = 1_700_000_000.0


def team() -> TeamConfig:
    robots = (
        RobotConfig("a", uwb_node="n_1", odom_topic="/a/odom"),
        RobotConfig("b", uwb_node="n_2", odom_topic="/b/odom"),
        RobotConfig("c", uwb_node="n_3", odom_topic="/c/odom", odom_zero_stamps=True),
    )
    return TeamConfig(robots=robots, reference="a")


def odom_payload(robot: str, t: float, x: float = 0.0) -> bytes:
    return encode(odometry_msg(OdometryEvent(t, robot, x, 0.0, 0.0)))


def range_payload(t: float, d: float = 3.0) -> bytes:
    return encode(range_msg(RangeEvent(t, "a", "b", d)))


class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr = key
        self.payload = _Bytes(payload)
        self.attachment = _Bytes(encode_sent_time(T0))


# ---------------------------------------------------------------------------- the rule
def test_wake_rule_bounds() -> None:
    rule = WakeRule(10.0, 10.1, 0.0, 20.0)
    assert not rule.urgent(9.99, odometry=False) and rule.urgent(10.0, odometry=False)
    assert not rule.urgent(10.05, odometry=True) and rule.urgent(10.1, odometry=True)
    assert rule.urgent(-0.1, odometry=True) and rule.urgent(20.1, odometry=True)
    assert rule.urgent(math.nan, odometry=True)  # outside every window
    assert WAKE_ALWAYS.urgent(5.0, odometry=True) and WAKE_ALWAYS.urgent(5.0, odometry=False)
    both = WakeRule.combine([rule, WakeRule(-math.inf, math.inf, 2.0, 30.0)])
    assert both == WakeRule(-math.inf, 10.1, 2.0, 20.0)


def test_localizer_rule_follows_the_batching_grid() -> None:
    sim, config = simulated_team(0, 5.0)
    loc = build_pipeline("pf", config, seed=0).localizer
    assert loc.wake_rule() == WAKE_ALWAYS  # the warm-up: the clock is not set
    events = [e for e in sim.events() if isinstance(e, OdometryEvent | RangeEvent)]
    k = 0
    while not loc.grid.pending or loc.clock.now == -math.inf:
        loc.process(events[k])
        k += 1
    period = UPDATE_PERIOD
    cell = math.floor(loc.grid.start / period)
    rule = loc.wake_rule()
    assert rule.measurement_from == pytest.approx((cell + 1) * period, abs=1e-4)
    assert rule.odometry_from == pytest.approx((cell + 2) * period, abs=1e-4)
    assert rule.urgent(loc.clock.now + MAX_TIME_JUMP + 0.1, odometry=True)
    loc.grid.pending.clear()  # nothing pending: every measurement opens a batch, no odometry fuses
    rule = loc.wake_rule()
    assert rule.measurement_from == -math.inf and rule.odometry_from == math.inf


@pytest.mark.parametrize(
    "faults",
    [
        Faults(),
        Faults(drop=0.2, seed=3),
        Faults(stamp_shift=((40, -0.35), (300, 0.25), (301, -7.0), (500, 9.0))),
    ],
    ids=["clean", "dropped", "shifted_stamps"],
)
def test_events_let_wait_never_make_an_estimate(faults: Faults) -> None:
    """Process the simulated team's events as the server does: an event waits unless the rule
    of the state after the last processed event says it is urgent; an urgent one is processed
    after those waiting, and the rule is read again. Every estimate must come from an urgent
    event, and the estimates are those of processing every event at once."""
    sim, config = simulated_team(1, 12.0)
    events = [e for e in sim.events() if isinstance(e, OdometryEvent | RangeEvent)]
    if faults.active:
        inject = FaultInjector(faults)
        events = [out for e in events if (out := inject(e)) is not None]
    direct = build_pipeline("pf", config, seed=0).localizer
    expected = [est for e in events for est in direct.process(e)]

    loc = build_pipeline("pf", config, seed=0).localizer
    rule, waiting, got, from_waiting, wakes = loc.wake_rule(), [], [], 0, 0
    for e in events:
        if not rule.urgent(e.t, isinstance(e, OdometryEvent)):
            waiting.append(e)
            continue
        wakes += 1
        for w in waiting:
            out = loc.process(w)
            from_waiting += len(out)
            got += out
        waiting = []
        got += loc.process(e)
        rule = loc.wake_rule()
    assert from_waiting == 0
    assert [repr(x) for x in got] == [repr(x) for x in expected[: len(got)]]
    assert len(expected) - len(got) <= 1  # at most one estimate among those still waiting
    assert len(got) > 50 and wakes < len(events) / 5  # far fewer wake-ups than events


# ---------------------------------------------------------------------------- the source
def test_the_wake_rule_judges_the_header_stamp_the_decoder_reads() -> None:
    """The callback's inlined stamp read is ``header_stamp_from_cdr``'s, to the last bit: a
    message stamped exactly at the rule's bound wakes the engine, one a microsecond before
    does not; bytes that are no CDR header wake it (judged by the decoder later)."""
    src = ZenohSource(team())
    for key, payload in (
        ("a/odom", odom_payload("a", T0 + 0.123456789)),
        ("uwb/tof/n_1/n_2/distance", range_payload(T0 + 2.5)),
    ):
        t = header_stamp_from_cdr(payload)
        odometry = key.endswith("odom")
        at = WakeRule(-math.inf if odometry else t, t if odometry else math.inf, T0 - 5.0, T0 + 5.0)
        before = WakeRule(*(b + 1e-6 if math.isfinite(b) and b == t else b for b in at))
        assert src._urgent(at, key, payload, 0.0) and not src._urgent(before, key, payload, 0.0)
    assert src._urgent(
        WakeRule(math.inf, math.inf, T0 - 5.0, T0 + 5.0), "a/odom", b"\x07\x01" + bytes(20), 0.0
    )


def test_source_wakes_only_for_urgent_messages_and_keeps_arrival_order() -> None:
    src = ZenohSource(team())
    # No rule yet: every message wakes the engine.
    src.on_sample(_Sample("a/odom", odom_payload("a", T0)))
    assert not src._wake.empty()
    src.poll(0.0)
    rule = WakeRule(T0 + 1.0, T0 + 2.0, T0 - 5.0, T0 + 5.0)
    src.rearm(rule)
    assert src._wake.empty()
    for t in (T0 + 0.5, T0 + 0.2, T0 + 0.9):  # odometry before odometry_from; out of stamp order
        src.on_sample(_Sample("b/odom", odom_payload("b", t)))
    src.on_sample(_Sample("uwb/tof/n_1/n_2/distance", range_payload(T0 + 0.95)))
    assert src._wake.empty() and src.queue_depth == 4  # nothing urgent: nobody woken
    # c's odometry is restamped from its receive time: judged by the header clock's offset
    # when the rule was set (only a's odometry seen then: its stamp T0 at its receive time).
    src.on_sample(_Sample("c/odom", odom_payload("c", 0.0)))
    assert src._wake.empty() and src.queue_depth == 5
    src.rearm(WakeRule(T0 + 1.0, T0 + 0.01, T0 - 5.0, T0 + 5.0))  # c's restamp would fuse now
    assert not src._wake.empty()
    released = src.poll(0.0)
    # Handled together, released in arrival order (no reorder window): b's second odometry is
    # older than its first and is passed on, counted out of order; so is c's, restamped from
    # its receive time to about T0 + 0.25 s (the odometry clock offset learnt from a and b).
    assert [(a.key, a.event.t) for a in released[:4]] == [
        ("b/odom", T0 + 0.5), ("b/odom", T0 + 0.2), ("b/odom", T0 + 0.9),
        ("uwb/tof/n_1/n_2/distance", T0 + 0.95),
    ]  # fmt: skip
    assert released[4].key == "c/odom" and src.queue_depth == 0
    assert src.stats.out_of_order == 2
    # A measurement at measurement_from wakes; so does one outside the clock window.
    src.on_sample(_Sample("uwb/tof/n_2/n_1/distance", range_payload(T0 + 1.0)))
    assert not src._wake.empty()
    src.poll(0.0)
    src.on_sample(_Sample("a/odom", odom_payload("a", T0 + 6.0)))
    assert not src._wake.empty()
    src.poll(0.0)
    # A message queued before the rule changed is judged again by rearm.
    src.on_sample(_Sample("a/odom", odom_payload("a", T0 + 2.5)))
    assert not src._wake.empty()
    src._wake.get_nowait()  # as if the token had been taken
    src.rearm(WakeRule(T0 + 1.0, T0 + 3.0, T0 - 5.0, T0 + 5.0))
    assert src._wake.empty()
    src.rearm(rule)
    assert not src._wake.empty()
    assert [a.event.t for a in src.drain()] == [T0 + 2.5]


def test_server_wakes_by_rule_only_where_events_reach_the_localizer_unchanged() -> None:
    sim, config = simulated_team(0, 5.0)

    class _Nothing:
        def declare_publisher(self, key: str) -> _Nothing:
            return self

        def put(self, payload: bytes, **kwargs: Any) -> None:
            pass

        def undeclare(self) -> None:
            pass

    assert LiveServer(config, _Nothing()).wake_by_rule
    assert not LiveServer(config, _Nothing(), ServeOptions(reorder_window=0.05)).wake_by_rule
    assert not LiveServer(config, _Nothing(), ServeOptions(faults=Faults(drop=0.1))).wake_by_rule
    server = LiveServer(config, _Nothing())
    # Fed through the source's queue as Zenoh would, rearmed after each wake: the estimates
    # are those of feeding every message as it comes.
    direct = LiveServer(config, _Nothing())
    for k, (t, channel, payload) in enumerate(event_messages(sim.events(), config, time_base=T0)):
        received = T0 + t + 0.001
        direct.source.handle(channel.key, payload, received)
        direct.feed(direct.source.release(received))
        server.source.on_sample(_Sample(channel.key, payload))
        server.source._inbox[-1] = (channel.key, payload, received, None)  # the receive time
        if not server.source._wake.empty() or k % 40 == 39:  # a wake, or a poll timeout
            server.feed(server.source.poll(0.0))
            server.source.rearm(server._wake_rule())
    server.feed(server.source.drain())
    direct.feed(direct.source.drain())
    mine, theirs = server.pipelines[0].estimates, direct.pipelines[0].estimates
    assert len(mine) > 20 and [repr(e) for e in mine] == [repr(e) for e in theirs]
