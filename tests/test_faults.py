"""Faults injected into the simulated team (:mod:`relloc.faults`): the clock, odometry resets
and jumps, range bursts, kidnapping, loss and silence never leave the localizer stuck or wrong.

Each run is the five-robot simulation (seeded) with a small particle count; the error of an
estimate is the mean over robots of its distance to the true relative position, smoothed over
1 s (the ambient error of a run is 0.1-0.17 m, so single estimates touch 0.2 m)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from waiting import wait_until

from relloc.estimators.particle.localizer import ParticleFilterLocalizer
from relloc.evaluation.metrics import GroundTruth
from relloc.events import GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.faults import Faults, Window, inject, parse
from relloc.navigation.safety import SafetyGate
from relloc.simulator import multi_scenario

PARTICLES = 3000


def _run(seed: int, faults: Faults, duration: float = 40.0, particles: int = PARTICLES):
    sim = multi_scenario(seed=seed, duration=duration)
    config = sim.config.with_filter(particles=particles)
    loc = ParticleFilterLocalizer(config, seed=seed)
    gt = GroundTruth(config.reference)
    for ev in inject(sim.events(), dataclasses.replace(faults, stamp_shift=(), stream_jump=())):
        if isinstance(ev, GroundTruthEvent):
            gt.add(ev)  # the truth on the stream's own clock: a kidnapping moves it
    ests = []
    for ev in inject(sim.events(), faults):
        if not isinstance(ev, GroundTruthEvent):
            ests += loc.process(ev)
    ests += loc.flush()
    return ests, gt, loc


def _errors(ests, gt: GroundTruth, shift: float = 0.0) -> np.ndarray:
    """(t, mean error over robots, recovering) per estimate, ``shift`` taken off its time."""
    rows = []
    for e in ests:
        t = e.t - shift
        errs = [
            math.hypot(p[0] - q[0], p[1] - q[1])
            for r, p in e.positions.items()
            if (q := gt.relative_at(r, t))
        ]
        if errs:
            rows.append((t, float(np.mean(errs)), float(e.recovering)))
    return np.array(rows)


def _smoothed(err: np.ndarray, width: float = 1.0) -> np.ndarray:
    t = err[:, 0]
    return np.array([err[(t > x - width) & (t <= x), 1].mean() for x in t])


def _back_under(err: np.ndarray, start: float, bound: float = 0.2) -> float:
    """Seconds after ``start`` from which the smoothed error stays under ``bound``."""
    smooth = _smoothed(err)
    after = err[:, 0] > start
    bad = err[after & (smooth >= bound), 0]
    return float(bad.max() - start) if bad.size else 0.0


def _kidnapped(kind: str) -> Faults:
    return {
        "burst1": Faults(range_burst=((Window(20.0, 22.0), 1.0),)),
        "burst3": Faults(range_burst=((Window(20.0, 22.0), 3.0),)),
        "reset": Faults(odom_reset=(("r2", 20.0),)),
        "step": Faults(odom_jump=(("r2", 20.0, 1000.0, 0.0),)),
        "kidnap": Faults(kidnap=(("r2", 20.0, 2.0, 0.0),)),
    }[kind]


# ---------------------------------------------------------------- the fault transforms
def test_faults_transform_the_stream_and_none_leaves_it_unchanged() -> None:
    sim = multi_scenario(seed=0, duration=3.0)
    events = list(sim.events())
    assert list(inject(events, Faults())) == events
    f = parse(
        drop=0.3,
        silence=["r1:1:2"],
        range_burst=["0.5:1:1.5"],
        odom_reset=["r2:1"],
        odom_jump=["r3:1:5:0"],
        kidnap=["r4:1:2:0"],
        stamp_shift=["10:3600"],
        seed=1,
    )
    out = list(inject(events, f))
    measured = [e for e in events if not isinstance(e, GroundTruthEvent)]
    kept = [e for e in out if not isinstance(e, GroundTruthEvent)]
    assert 0.6 * len(measured) < len(kept) < 0.72 * len(measured)
    assert not any(
        "r1" in (getattr(e, "robot", ""), getattr(e, "robot_a", ""), getattr(e, "robot_b", ""))
        and 1.0 <= e.t < 2.0
        for e in kept
        if not isinstance(e, GroundTruthEvent)
    )
    r2 = [e for e in kept if isinstance(e, OdometryEvent) and e.robot == "r2" and e.t >= 1.0]
    assert r2 and math.hypot(r2[0].x, r2[0].y) < 0.05  # restarted at the origin
    r3 = [e for e in kept if isinstance(e, OdometryEvent) and e.robot == "r3" and e.t >= 1.0]
    assert all(e.x > 4.0 for e in r3)
    burst = [e for e in kept if isinstance(e, RangeEvent) and 0.5 <= e.t < 1.0]
    clean = {(e.t, e.robot_a, e.robot_b): e.distance for e in measured if isinstance(e, RangeEvent)}
    assert all(abs(e.distance - clean[(e.t, e.robot_a, e.robot_b)] - 1.5) < 1e-9 for e in burst)
    with pytest.raises(ValueError, match="silence"):
        parse(silence=["r1:1"])


# ---------------------------------------------------------------- the clock
def _feed(config, events, seed: int = 0):
    loc = ParticleFilterLocalizer(config, seed=seed)
    ests = []
    for ev in events:
        if not isinstance(ev, GroundTruthEvent):
            ests += loc.process(ev)
    return ests + loc.flush(), loc


@pytest.mark.parametrize(
    "shifts",
    [
        {400: 3600.0},  # one message an hour ahead
        {400: -3600.0},  # one an hour behind
        {300: 120.0, 400: 300.0, 500: 480.0},  # three ahead, minutes apart
        {0: 3600.0},  # the first measurement in the future
    ],
    ids=["future", "past", "three_future", "first_future"],
)
def test_stamp_outliers_are_rejected_and_change_nothing_else(shifts: dict[int, float]) -> None:
    """A message with a wrong stamp is rejected (counted) and has no other effect: the
    estimates are exactly those of the run without that message."""
    sim = multi_scenario(seed=0, duration=20.0)
    config = sim.config.with_filter(particles=PARTICLES)
    events = [e for e in sim.events() if not isinstance(e, GroundTruthEvent)]
    shifted = [
        dataclasses.replace(e, t=e.t + shifts[i]) if i in shifts else e
        for i, e in enumerate(events)
    ]
    without = [e for i, e in enumerate(events) if i not in shifts]
    ests, loc = _feed(config, shifted)
    ref, _ = _feed(config, without)
    assert [(e.t, e.positions) for e in ests] == [(e.t, e.positions) for e in ref]
    assert sum(loc.rejected.values()) == len(shifts)
    assert set(loc.rejected) <= {
        "time_jump",
        "time_jump_backward",
        "out_of_order_odometry",
        "late_measurement",
    }
    assert "clock_jumps_followed" not in loc.stats


@pytest.mark.parametrize("dt", [3600.0, -3600.0])
def test_a_whole_stream_clock_step_is_followed_within_a_second(dt: float) -> None:
    ests, gt, loc = _run(0, Faults(stream_jump=((15.0, dt),)), duration=25.0)
    assert loc.stats["clock_jumps_followed"] == 1
    after = [e.t - dt for e in ests if e.t - dt >= 15.0 and abs(e.t - dt) < 100]
    assert after and after[0] < 16.0
    err = _errors([e for e in ests if e.t - dt >= 15.0], gt, shift=dt)
    assert err[:, 1].mean() < 0.2


def test_a_followed_clock_step_moves_every_remembered_time_with_it() -> None:
    """r2 silent 8-11 s pauses the orientation kernel until 13 s; the stream then steps back
    1 h at 15 s. The times the localizer keeps (last range per robot, the kernel's pause, the
    trust hold, the monitor's restart) move with the clock, so the kernel runs again after the
    step instead of waiting for the old clock to come round (an hour)."""
    dt = -3600.0
    sim = multi_scenario(seed=0, duration=22.0)
    loc = ParticleFilterLocalizer(sim.config.with_filter(particles=PARTICLES), seed=0)
    faults = Faults(silence=(Window(8.0, 11.0, "r2"),), stream_jump=((15.0, dt),))
    paused_after = []
    for ev in inject(sim.events(), faults):
        if not isinstance(ev, GroundTruthEvent):
            loc.process(ev)
            if loc.initialized and ev.t < 0.0 and ev.t - dt > 17.0:  # after the step
                paused_after.append(loc.filter.kernel_paused)
    assert loc.stats["clock_jumps_followed"] == 1
    assert paused_after and not any(paused_after)
    assert loc.heard.split_at < loc.t and loc.recovery.monitor._restarted <= loc.t


# ---------------------------------------------------------------- odometry
@pytest.mark.parametrize("kind", ["reset", "step"])
def test_odometry_reset_or_jump_re_anchors_the_track(kind: str) -> None:
    ests, gt, loc = _run(1, _kidnapped(kind), duration=30.0)
    assert loc.stats["odometry_reanchored"] == 1 and loc.odometry_faults == {"r2": 1}
    assert _back_under(_errors(ests, gt), 20.0) <= 5.0


# ---------------------------------------------------------------- divergence and recovery
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["burst1", "burst3", "kidnap"])
def test_divergence_is_flagged_and_recovered_within_10_s(kind: str) -> None:
    """All ranges 1 m or 3 m long for 2 s, or r2 moved 2 m unseen, on seeds 0-2: the loss is
    flagged within 2 s of the onset every time (by the divergence monitor, ``recovering``, or
    first by the consistency watchdog, ``inconsistent``) and counted, and the error is back
    under 0.2 m within 10 s of the fault's end (measured: 1.0-5.5 s, docs/howto/faults.md)."""
    end = 22.0 if kind.startswith("burst") else 20.0
    settled = []
    for seed in (0, 1, 2):
        ests, gt, loc = _run(seed, _kidnapped(kind))
        err = _errors(ests, gt)
        flagged = err[(err[:, 2] > 0) | np.array([e.inconsistent for e in ests]), 0]
        assert flagged.size and 0.0 <= flagged.min() - 20.0 <= 2.0, seed
        counters = loc.fault_counters()
        assert counters["divergence_detected"] + counters["inconsistency_restarts"] >= 1, seed
        assert counters["recovery_injections"] >= 1
        assert _back_under(err, end) <= 10.0, seed
        settled.append(float(err[err[:, 0] > 35.0, 1].mean()))
    # after 35 s, all but one seed and the mean under 0.15 m: one seed's figure is the luck of
    # its draws (kidnap: 0.161 / 0.072 / 0.058 m with the compiled step, its seed 0 near the
    # NumPy step's worst of seeds 0-7)
    assert sum(e < 0.15 for e in settled) >= 2 and np.mean(settled) < 0.15, settled


def test_no_divergence_is_flagged_on_clean_runs() -> None:
    for seed in (0, 1, 2):
        _, _, loc = _run(seed, Faults(), duration=30.0)
        assert loc.stats["divergence_detected"] == 0 and loc.stats["recovery_injections"] == 0, seed
        assert loc.fault_counters()["inconsistency_detected"] == 0, seed  # nor by the watchdog


def test_the_navigation_gate_holds_while_recovering() -> None:
    ests, _, _ = _run(0, _kidnapped("kidnap"), duration=25.0)
    flagged = next(e for e in ests if e.recovering or e.inconsistent)
    gate = SafetyGate(robot="r2")
    assert gate.check(flagged.t, flagged, flagged.t) in (
        ("recovering", "the localizer found itself lost and is recovering"),
        ("inconsistent", "the estimate's covariance no longer covers its innovations"),
    )


# ---------------------------------------------------------------- loss and silence
def test_loss_and_a_silence_cost_little_outside_the_silence() -> None:
    clean, gt, _ = _run(0, Faults(), duration=40.0)
    lossy, _, _ = _run(0, Faults(drop=0.3, seed=3), duration=40.0)
    quiet, _, _ = _run(0, Faults(silence=(Window(20.0, 30.0, "r2"),)), duration=40.0)
    a = _errors(clean, gt)
    base = a[a[:, 0] > 10, 1].mean()
    b = _errors(lossy, gt)
    assert abs(b[b[:, 0] > 10, 1].mean() - base) < 0.03
    c = _errors(quiet, gt)
    outside = (c[:, 0] > 10) & ((c[:, 0] < 20) | (c[:, 0] > 30))
    ref = (a[:, 0] > 10) & ((a[:, 0] < 20) | (a[:, 0] > 30))
    assert abs(c[outside, 1].mean() - a[ref, 1].mean()) < 0.03


# ---------------------------------------------------------------- relloc replay
def test_replay_publishes_the_faulted_messages_over_zenoh(
    tmp_path: Path, bag_writer: Callable[..., Path], sessions: tuple[Any, Any]
) -> None:
    """``relloc replay`` with faults: the messages a live source receives over loopback Zenoh
    decode to exactly the bag's events with the faults applied (a loss, a silence, a range
    burst, an odometry reset and jump, a kidnapping, a stamp shift), values to float32 (a
    range's precision in ``sensor_msgs/Range``)."""
    from relloc.live.publish import (
        SIM_TIME_BASE,
        EventEncoder,
        ReplayOptions,
        replay_bag,
        simulated_team,
    )
    from relloc.ros.messages import decode
    from relloc.sources.rosbag import RosbagSource
    from relloc.sources.zenoh_source import ZenohSource

    sim, config = simulated_team(0, 6.0)
    config = config.with_robot("r2", mocap_body="r2").with_robot("r0", mocap_body="r0")
    encoder = EventEncoder(config, ground_truth=True)
    messages = []
    for ev in sim.events():
        out = encoder.encode(ev, SIM_TIME_BASE)
        if out is not None and (not isinstance(ev, GroundTruthEvent) or ev.robot in ("r0", "r2")):
            channel, payload = out
            messages.append(
                (channel.name, channel.msgtype, ev.t + 0.01, decode(payload, channel.msgtype))
            )
    bag = bag_writer(tmp_path / "sim", messages)
    t0 = SIM_TIME_BASE
    faults = parse(
        drop=0.2,
        silence=[f"r1:{t0 + 1}:{t0 + 2}"],
        range_burst=[f"{t0 + 2}:{t0 + 3}:1.5"],
        odom_reset=[f"r3:{t0 + 3}"],
        odom_jump=[f"r4:{t0 + 4}:2:0"],
        kidnap=[f"r2:{t0 + 4.5}:1:0"],
        stamp_shift=["200:0.05"],
        seed=4,
    )
    srv, client = sessions
    source = ZenohSource(config)
    source.attach(srv)
    try:
        stats = replay_bag(bag, config, client, ReplayOptions(rate=20.0, wait=5.0, faults=faults))
        assert wait_until(lambda: source.queue_depth >= stats.messages, timeout=10.0)
        received = [a.event for a in source.drain()]
    finally:
        source.detach()
    expected = list(inject(RosbagSource(bag, config), faults))

    def key(
        e: Any,
    ) -> tuple:  # values at float32 (a range's precision on the wire), the stamp exact
        values = dataclasses.astuple(e)
        return (
            type(e).__name__,
            values[0],
            *(float(np.float32(v)) if isinstance(v, float) else v for v in values[1:]),
        )

    assert sorted(map(key, received)) == sorted(
        map(key, (e for e in expected if not isinstance(e, GroundTruthEvent)))
    )
    counts = stats.injected
    assert counts["dropped"] > 100 and counts["silenced"] > 20 and counts["shifted"] == 1
    assert counts["changed"] > 100
    ranges = [
        e
        for e in received
        if isinstance(e, RangeEvent) and "r2" in (e.robot_a, e.robot_b) and e.t > t0 + 5
    ]
    clean = {
        (e.t, e.robot_a, e.robot_b): e.distance
        for e in RosbagSource(bag, config)
        if isinstance(e, RangeEvent)
    }
    assert any(
        abs(e.distance - clean[(e.t, e.robot_a, e.robot_b)]) > 0.3 for e in ranges
    )  # kidnapped


# ---------------------------------------------------------------- the live shortbag
SHORTBAG = "multi4_shortbag_20221011"


def _shortbag_error(
    shared_data: Path, seed: int, faults: Faults, outside: tuple[float, float]
) -> tuple[float, Any]:
    """Mean over estimates after ``outside[1]`` s (and after the 5 s warm-up, before
    ``outside[0]``) of the mean error over robots, on the shortbag's events through the
    localizer (the events a live replay gives the server) with ``faults`` injected."""
    from relloc.config import TeamConfig
    from relloc.sources.rosbag import RosbagSource

    config = TeamConfig.load(
        Path(__file__).resolve().parents[1] / "configs" / "tiers" / f"{SHORTBAG}.toml"
    )
    source = RosbagSource(shared_data / "tiers" / SHORTBAG, config)
    t0 = source.start_time
    events = list(source)
    gt = GroundTruth(config.reference)
    loc = ParticleFilterLocalizer(config, seed=seed)
    ests = []
    for ev in inject(
        events,
        dataclasses.replace(
            faults, silence=tuple(Window(t0 + w.start, t0 + w.end, w.robot) for w in faults.silence)
        ),
    ):
        if isinstance(ev, GroundTruthEvent):
            gt.add(ev)
        else:
            ests += loc.process(ev)
    ests += loc.flush()
    err = _errors(ests, gt)
    err[:, 0] -= t0
    keep = (err[:, 0] > 5.0) & ((err[:, 0] < outside[0]) | (err[:, 0] > outside[1]))
    return float(err[keep, 1].mean()), loc


@pytest.mark.slow
@pytest.mark.shared_data
def test_a_10_s_silence_on_the_shortbag_costs_little_after_it(shared_data: Path) -> None:
    """turtle05 (the far, static robot) silent 5-15 s of the 17.5 s shortbag, seeds 0-2:
    after it the error is within 0.03 m of the clean run's on the seeds' mean, within 0.05 m
    on every seed (measured gaps 0.016 / 0.024 / 0.017 m with the NumPy step, -0.019 / 0.035 /
    0.033 m with the compiled one, seeds 0-7 0.011 and 0.012 m on average; 0.104 / 0.125 /
    0.050 m before the orientation kernel paused for a silent robot, docs/howto/faults.md),
    and no divergence is flagged, clean or silent."""
    silence = Faults(silence=(Window(5.0, 15.0, "turtle05"),))
    gaps = []
    for seed in (0, 1, 2):
        clean, loc_clean = _shortbag_error(shared_data, seed, Faults(), (5.0, 15.0))
        quiet, loc_quiet = _shortbag_error(shared_data, seed, silence, (5.0, 15.0))
        assert loc_clean.stats["divergence_detected"] == loc_quiet.stats["divergence_detected"] == 0
        gaps.append(quiet - clean)
    assert float(np.mean(gaps)) <= 0.03 and max(gaps) <= 0.05, gaps


def test_the_orientation_kernel_waits_while_a_robot_is_out_of_ranging() -> None:
    """r2 silent 10-20 s: the kernel pauses 2 s into the silence and resumes 2 s after r2's
    ranges are back; it never pauses on the clean run."""
    sim = multi_scenario(seed=0, duration=26.0)
    config = sim.config.with_filter(particles=PARTICLES)
    for faults, expect_pause in (
        (Faults(), False),
        (Faults(silence=(Window(10.0, 20.0, "r2"),)), True),
    ):
        loc = ParticleFilterLocalizer(config, seed=0)
        paused = []
        for ev in inject(sim.events(), faults):
            if not isinstance(ev, GroundTruthEvent):
                loc.process(ev)
                if loc.initialized:
                    paused.append((ev.t, loc.filter.kernel_paused))
        times = [t for t, p in paused if p]
        if not expect_pause:
            assert not times
            continue
        assert 12.0 <= min(times) <= 12.3 and 21.9 <= max(times) <= 22.3, (min(times), max(times))
