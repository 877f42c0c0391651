"""What every simulated sensor will measure, drawn once when the simulation is built.

Each function draws one sensor's sample times and noise for the whole run, every quantity from
its own stream (:mod:`relloc.simulator.streams`, keyed by the seed, what it is and whose it
is), so the stepping of :class:`~relloc.simulator.runner.Simulation` only reads them: a run
returns the same events however it is cut into steps, and a scenario that adds a sensor draws
exactly what it drew before for the others.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from itertools import combinations
from typing import Any

import numpy as np
from numpy.typing import NDArray

from relloc.events import pair_key
from relloc.simulator.error_models import (
    ActuationModel,
    DetectionErrorModel,
    OdometryErrorModel,
    SightingSensorModel,
    UwbErrorModel,
    UwbPair,
)
from relloc.simulator.kinematics import RobotMotion
from relloc.simulator.streams import stream

FloatArray = NDArray[np.float64]

Schedule = dict[str, NDArray[Any]]
"""Sample times ``"t"`` and, per sample, the draws a sensor's model reads (by name): floats,
or booleans for the events drawn as such (a miss, an outlier)."""
Sightings = list[tuple[SightingSensorModel, str, str, Schedule]]
"""Per sighting sensor and ordered (observer, target) pair: its schedule."""


def draw_odometry(
    seed: int, motions: Sequence[RobotMotion], model: OdometryErrorModel, duration: float
) -> tuple[dict[str, float], dict[str, float], dict[str, Schedule]]:
    """Per robot: its wheel-scale factor, its gyro bias (rad/s), and its odometry schedule
    (sample times at the model's rate with a random phase, velocity and yaw-rate noise)."""
    scales: dict[str, float] = {}
    gyro_biases: dict[str, float] = {}
    schedules: dict[str, Schedule] = {}
    period = 1.0 / model.rate_hz
    for m in motions:
        rng = stream(seed, "odom-params", m.name)
        scales[m.name] = float(rng.uniform(*model.scale_range))
        gyro_biases[m.name] = float(rng.uniform(-model.gyro_bias_max, model.gyro_bias_max))
        phase = rng.uniform(0.0, period)
        times = np.arange(phase, duration + 1e-9, period)
        schedules[m.name] = {
            "t": times,
            "nv": stream(seed, "odom-v", m.name).standard_normal(times.size),
            "nw": stream(seed, "odom-w", m.name).standard_normal(times.size),
        }
    return scales, gyro_biases, schedules


def draw_uwb(
    seed: int, motions: Sequence[RobotMotion], model: UwbErrorModel, duration: float
) -> tuple[dict[str, float], list[UwbPair]]:
    """The true bias of every node pair (by pair key) and every pair's drawn parameters:
    orientation amplitudes, antenna offsets, jittered sample times, noise, NLOS spikes and
    dropouts."""
    period = 1.0 / model.rate_hz
    tags = [(m, node, arm) for m in motions for node, arm in m.tag_list]
    antenna = {n: float(stream(seed, "uwb-antenna", n).uniform(-0.5, 0.5)) for _, n, _ in tags}
    biases: dict[str, float] = {}
    pairs: list[UwbPair] = []
    for (ma, na, arm_a), (mb, nb, arm_b) in combinations(tags, 2):
        if ma is mb:
            continue  # two tags of one robot: their distance is a constant of its body
        key = pair_key(na, nb)
        bias = float(stream(seed, "uwb-bias", key).uniform(*model.bias_range))
        biases[key] = bias
        amp = stream(seed, "uwb-orient", key).uniform(0.5, 1.5, size=2)
        rng_t = stream(seed, "uwb-time", key)
        phase = rng_t.uniform(0.0, period)
        base = np.arange(phase, duration + period, period)
        jitter = np.clip(rng_t.normal(0.0, model.jitter, base.size), -period / 4, period / 4)
        times = base + jitter
        n = times.size
        spikes = stream(seed, "uwb-nlos", key).uniform(0.0, 1.0, size=(n, 2))
        nlos = spikes[:, 0] < model.nlos_probability
        lo, hi = model.nlos_range
        mask = (times >= 0.0) & (times <= duration)
        pairs.append(
            UwbPair(
                robot_a=ma.name,
                robot_b=mb.name,
                node_a=na,
                node_b=nb,
                bias=bias,
                amplitude=amp * model.orientation_amplitude,
                antenna=np.array([antenna[na], antenna[nb]]),
                t=times[mask],
                noise=(stream(seed, "uwb-noise", key).standard_normal(n) * model.sigma)[mask],
                spike=np.where(nlos, lo + spikes[:, 1] * (hi - lo), 0.0)[mask],
                keep=(
                    stream(seed, "uwb-dropout", key).uniform(size=n) >= model.dropout_probability
                )[mask],
                arm_a=arm_a,
                arm_b=arm_b,
            )
        )
    return biases, pairs


def draw_camera(
    seed: int,
    motions: Sequence[RobotMotion],
    model: DetectionErrorModel,
    n_objects: int,
    duration: float,
) -> dict[str, Schedule]:
    """Per robot, its camera's frame times and, per frame and object, miss, depth, bearing and
    height noise and the detector's score."""
    period = 1.0 / model.rate_hz
    out: dict[str, Schedule] = {}
    for m in motions:
        rng_t = stream(seed, "camera-time", m.name)
        phase = rng_t.uniform(0.0, period)
        times = np.arange(phase, duration + 1e-9, period)
        rng = stream(seed, "camera-noise", m.name)
        shape = (times.size, n_objects)
        out[m.name] = {
            "t": times,
            "miss": rng.uniform(size=shape) < model.miss_probability,
            "nd": rng.standard_normal(shape),
            "nb": rng.standard_normal(shape),
            "nz": rng.standard_normal(shape),
            "score": rng.uniform(0.5, 0.95, size=shape),
        }
    return out


def draw_sightings(
    seed: int, robots: Sequence[str], models: Sequence[SightingSensorModel], duration: float
) -> Sightings:
    """Per sensor and ordered pair: sample times and noise, each from its own stream (so a
    scenario without them draws exactly what it drew before they existed)."""
    out: Sightings = []
    for sm in models:
        period = 1.0 / sm.rate_hz
        for obs in robots:
            for tgt in robots:
                if obs == tgt:
                    continue
                rng_t = stream(seed, "sighting-time", sm.sensor, obs, tgt)
                times = np.arange(rng_t.uniform(0.0, period), duration + 1e-9, period)
                rng = stream(seed, "sighting-noise", sm.sensor, obs, tgt)
                n = times.size
                out.append(
                    (
                        sm,
                        obs,
                        tgt,
                        {
                            "t": times,
                            "nr": rng.standard_normal(n),
                            "nb": rng.standard_normal(n),
                            "outlier": rng.uniform(size=n) < sm.outlier_probability,
                            "wild": rng.uniform(-0.5, 0.5, size=n),
                            "miss": rng.uniform(size=n) < sm.miss_probability,
                        },
                    )
                )
    return out


def draw_actuation(
    seed: int, commanded: Sequence[str], model: ActuationModel, duration: float
) -> dict[str, FloatArray]:
    """Per commanded robot, the standard-normal draws ``(steps, 3)`` of its actuation noise."""
    n = math.ceil(duration / model.dt) + 2
    return {name: stream(seed, "actuation", name).standard_normal((n, 3)) for name in commanded}
