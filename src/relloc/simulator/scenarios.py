"""The paper's scenarios as simulations.

:func:`multi_scenario` is the paper's five-robot experiment in the 8 m x 9 m arena (a static
reference robot and four robots on a triangle, an X, a circle and a rectangle),
:func:`single_scenario` the two-robot single-range experiment, and :func:`nav_scenario` the
multi team with one robot driven by velocity commands. :func:`static_scenario` parks the multi
team for the whole run and :func:`static_then_move_scenario` parks it for 20 s before the
robots drive their patterns: at rest the formation's orientation about the reference is not
observable from ranges, and these scenarios test that the estimate says so.
:func:`grid_scenario` is the scaling scenario: ``N`` robots on a grid, all pairs ranging.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any, Literal

import numpy as np

from relloc.simulator.error_models import (
    ActuationModel,
    DetectionErrorModel,
    OdometryErrorModel,
    SightingSensorModel,
    UwbErrorModel,
)
from relloc.simulator.flight import drones_scenario, drones_six_scenario, drones_uwb_scenario
from relloc.simulator.kinematics import (
    RobotMotion,
    SimObject,
    circle_loop,
    looped_motion,
    polygon_loop,
)
from relloc.simulator.runner import Simulation
from relloc.simulator.streams import stream


def _initial_yaw(seed: int, name: str, heading_offsets: str) -> float | None:
    if heading_offsets == "start":
        return None
    if heading_offsets == "random":
        return float(stream(seed, "initial-yaw", name).uniform(-math.pi, math.pi))
    raise ValueError(f"heading_offsets must be 'start' or 'random', got {heading_offsets!r}")


def _place_objects(
    seed: int, nominal: Sequence[SimObject], jitter: float = 0.15
) -> list[SimObject]:
    """The nominal objects, each moved by up to ``jitter`` metres (seeded)."""
    rng = stream(seed, "objects")
    offsets = rng.uniform(-jitter, jitter, size=(len(nominal), 2))
    return [
        SimObject(o.label, o.x + float(dx), o.y + float(dy), o.z)
        for o, (dx, dy) in zip(nominal, offsets, strict=True)
    ]


TURN_RATE = 0.6
"""Turn-in-place rate at pattern corners (rad/s)."""

MULTI_OBJECTS: tuple[SimObject, ...] = (
    SimObject("chair", 2.2, 0.7, 0.45),
    SimObject("chair", 0.0, 2.4, 0.45),
    SimObject("bottle", 0.25, -1.6, 0.75),
    SimObject("backpack", -2.7, 0.2, 0.25),
    SimObject("suitcase", 1.4, -0.2, 0.35),
    SimObject("potted plant", -2.5, 3.7, 0.5),
    SimObject("tv", 3.55, 3.2, 0.8),
    SimObject("cup", 4.4, -2.0, 0.75),
)
"""Nominal objects of the multi scenario (each moved by up to 0.15 m per seed).

Placed (by a small search over layouts, at least 0.45 m from every path) so that pairs of
robots see a common object at the same time for much of the run (:func:`covisibility`
measures how much; the figures are in docs/explanation/measurements.md).
"""


def multi_scenario(
    seed: int = 0,
    *,
    duration: float = 60.0,
    detections: bool = False,
    heading_offsets: Literal["start", "random"] = "start",
    uwb: UwbErrorModel | None = None,
    commanded: Sequence[str] = (),
    odometry: OdometryErrorModel | None = None,
    camera: DetectionErrorModel | None = None,
    actuation: ActuationModel | None = None,
    sightings: Sequence[SightingSensorModel] = (),
    tags: float = 0.0,
    odometry_topics: bool = True,
    name: str | None = None,
) -> Simulation:
    """The paper's five-robot experiment in the 8 m x 9 m arena.

    ``tags`` > 0: every robot carries two UWB tags that far apart, either side of its centre
    on its x axis (``n_<i>a`` ahead, ``n_<i>b`` behind), instead of one at its centre;
    ``odometry_topics`` False: the robots report no odometry.

    ``sightings``: sensors that see teammates (UWB angle of arrival beside the ranges, a
    camera; :mod:`relloc.simulator.error_models`), drawn from their own streams.

    ``r0`` (node ``n_0``) is static and the reference; ``r1`` drives a triangle, ``r2`` an X
    (both diagonals of a square joined by two of its sides), ``r3`` a circle and ``r4`` a
    rectangle, one per quarter of the arena, each 2-2.5 m across at 0.22-0.28 m/s, turning in
    place at the corners and looping until the end (each from a seeded point of its loop).

    ``heading_offsets="start"``: robots start heading along their pattern (``r0``, at (1.0, -0.6),
    faces 75 degrees); ``"random"``: every robot starts with a random heading (the moving
    ones first turn onto their pattern). Either way the odometry frame is the start pose, so
    the heading offset is the initial yaw, given truthfully in ``config``.
    Robots named in ``commanded`` start where their pattern would and obey
    :meth:`Simulation.set_command` instead.
    """
    unknown = set(commanded) - {"r0", "r1", "r2", "r3", "r4"}
    if unknown:
        raise ValueError(f"unknown commanded robot(s) {sorted(unknown)}; the team is r0..r4")
    loops = {
        "r1": (
            "triangle",
            polygon_loop([(-3.2, 1.4), (-0.8, 1.4), (-2.0, 3.48)], 0.25, TURN_RATE),
        ),
        "r2": (
            "x",
            polygon_loop([(1.0, 1.3), (3.0, 3.3), (3.0, 1.3), (1.0, 3.3)], 0.22, TURN_RATE),
        ),
        "r3": ("circle", circle_loop(-2.0, -2.4, 1.1, 0.25)),
        "r4": (
            "rectangle",
            polygon_loop([(0.8, -3.3), (3.2, -3.3), (3.2, -1.5), (0.8, -1.5)], 0.28, TURN_RATE),
        ),
    }
    yaw0 = _initial_yaw(seed, "r0", heading_offsets)
    motions = [
        RobotMotion(
            "r0",
            "n_0",
            1.0,
            -0.6,
            math.radians(75.0) if yaw0 is None else yaw0,
            commanded="r0" in commanded,
            pattern="static",
        )
    ]
    for i, (name, (pattern, loop)) in enumerate(loops.items(), start=1):
        motions.append(
            looped_motion(
                name,
                f"n_{i}",
                pattern,
                loop,
                seed=seed,
                duration=duration,
                initial_yaw=_initial_yaw(seed, name, heading_offsets),
                turn_rate=TURN_RATE,
                commanded=name in commanded,
            )
        )
    if tags > 0.0:
        motions = [
            dataclasses.replace(
                m,
                tags=((f"{m.node}a", (tags / 2, 0.0)), (f"{m.node}b", (-tags / 2, 0.0))),
            )
            for m in motions
        ]
    return Simulation(
        motions,
        reference="r0",
        seed=seed,
        duration=duration,
        odometry_topics=odometry_topics,
        name=name or ("sim_multi" if not commanded else "sim_nav"),
        objects=_place_objects(seed, MULTI_OBJECTS),
        detections=detections,
        uwb=uwb,
        odometry=odometry,
        camera=camera,
        actuation=actuation,
        sightings=sightings,
    )


SINGLE_OBJECTS: tuple[SimObject, ...] = (
    SimObject("chair", 0.5, 0.0, 0.45),
    SimObject("bottle", 0.0, 1.6, 0.75),
    SimObject("backpack", 0.2, -1.7, 0.25),
    SimObject("suitcase", -3.3, 0.0, 0.35),
)


def single_scenario(
    seed: int = 0,
    *,
    duration: float = 45.0,
    detections: bool = False,
    heading_offsets: Literal["start", "random"] = "start",
    uwb: UwbErrorModel | None = None,
    commanded: Sequence[str] = (),
    odometry: OdometryErrorModel | None = None,
    camera: DetectionErrorModel | None = None,
    actuation: ActuationModel | None = None,
) -> Simulation:
    """The single-range experiment: ``r0`` static (the reference), ``r1`` driving circles.

    ``r1`` drives counter-clockwise circles of 1 m radius at 0.22 m/s (about 10 m in 45 s,
    like the real recording) about 2.5 m from ``r0``; one UWB pair (``n_0-n_1``) at 10 Hz.
    """
    yaw0 = _initial_yaw(seed, "r0", heading_offsets)
    motions = [
        RobotMotion(
            "r0",
            "n_0",
            1.5,
            0.0,
            math.pi if yaw0 is None else yaw0,
            commanded="r0" in commanded,
            pattern="static",
        ),
        looped_motion(
            "r1",
            "n_1",
            "circle",
            circle_loop(-1.0, 0.0, 1.0, 0.22),
            seed=seed,
            duration=duration,
            initial_yaw=_initial_yaw(seed, "r1", heading_offsets),
            turn_rate=TURN_RATE,
            commanded="r1" in commanded,
        ),
    ]
    return Simulation(
        motions,
        reference="r0",
        seed=seed,
        duration=duration,
        name="sim_single",
        objects=_place_objects(seed, SINGLE_OBJECTS, jitter=0.1),
        detections=detections,
        uwb=uwb,
        odometry=odometry,
        camera=camera,
        actuation=actuation,
    )


def nav_scenario(
    seed: int = 0,
    *,
    robot: str = "r2",
    duration: float = 60.0,
    detections: bool = False,
    heading_offsets: Literal["start", "random"] = "start",
    uwb: UwbErrorModel | None = None,
    odometry: OdometryErrorModel | None = None,
    camera: DetectionErrorModel | None = None,
    actuation: ActuationModel | None = None,
) -> Simulation:
    """The multi team with ``robot`` (default ``r2``) driven by :meth:`Simulation.set_command`.

    For closed-loop navigation on the relative estimate: call :meth:`Simulation.advance` in
    steps, feed the events to the localizer, and command the robot from its estimate.
    """
    return multi_scenario(
        seed,
        duration=duration,
        detections=detections,
        heading_offsets=heading_offsets,
        uwb=uwb,
        commanded=(robot,),
        odometry=odometry,
        camera=camera,
        actuation=actuation,
    )


def _parked_multi(
    seed: int,
    park: float,
    duration: float,
    name: str,
    detections: bool,
    heading_offsets: Literal["start", "random"],
    uwb: UwbErrorModel | None,
    odometry: OdometryErrorModel | None,
) -> Simulation:
    """The multi team, each robot at its seeded start pose, parked for ``park`` s (the whole run
    if ``park >= duration``) and then driving its pattern as in :func:`multi_scenario`."""
    base = multi_scenario(
        seed, duration=duration + park, detections=detections, heading_offsets=heading_offsets
    )
    motions = [
        replace(m, segments=(), pattern="parked")
        if park >= duration or not m.segments
        else replace(m, segments=((park, 0.0, 0.0), *m.segments))
        for m in base.motions
    ]
    return Simulation(
        motions,
        reference="r0",
        seed=seed,
        duration=duration,
        name=name,
        objects=_place_objects(seed, MULTI_OBJECTS),
        detections=detections,
        uwb=uwb,
        odometry=odometry,
    )


def static_scenario(
    seed: int = 0,
    *,
    duration: float = 30.0,
    detections: bool = False,
    heading_offsets: Literal["start", "random"] = "start",
    uwb: UwbErrorModel | None = None,
    odometry: OdometryErrorModel | None = None,
) -> Simulation:
    """The multi team's five robots parked for the whole run (each at the seeded start of its
    pattern), ranges between all of them: the shape is known, the orientation of the formation
    about the reference (and its mirror image) is not."""
    return _parked_multi(
        seed, duration, duration, "sim_static", detections, heading_offsets, uwb, odometry
    )


STATIC_THEN_MOVE_PARK_S = 20.0
"""How long :func:`static_then_move_scenario` keeps the team parked before it drives (s)."""


def static_then_move_scenario(
    seed: int = 0,
    *,
    duration: float = 60.0,
    detections: bool = False,
    heading_offsets: Literal["start", "random"] = "start",
    uwb: UwbErrorModel | None = None,
    odometry: OdometryErrorModel | None = None,
) -> Simulation:
    """The multi team parked for ``STATIC_THEN_MOVE_PARK_S`` (20 s), then every robot but the
    reference drives its pattern: the motion resolves the orientation."""
    return _parked_multi(
        seed,
        STATIC_THEN_MOVE_PARK_S,
        duration,
        "sim_static_then_move",
        detections,
        heading_offsets,
        uwb,
        odometry,
    )


GRID_SPACING = 3.0
"""Distance between neighbouring cells of :func:`grid_scenario` (m)."""


def grid_scenario(
    seed: int = 0,
    *,
    robots: int = 5,
    duration: float = 40.0,
    spacing: float = GRID_SPACING,
    detections: bool = False,
    heading_offsets: Literal["start", "random"] = "start",
    uwb: UwbErrorModel | None = None,
    odometry: OdometryErrorModel | None = None,
) -> Simulation:
    """A team of ``robots`` on a square grid, every pair ranging: the scaling scenario.

    The cells are ``spacing`` metres apart, ``ceil(sqrt(robots))`` to a row, filled row by row
    and centred on the origin. ``r0`` (node ``n_0``) sits static at the centre of the first
    cell and is the reference; every other robot ``r<i>`` drives counter-clockwise circles about
    the centre of its own cell, radius 0.7-1.1 m and speed 0.2-0.3 m/s (drawn from the robot's
    own ``grid-circle`` stream), from a seeded point of its circle. Positions, odometry and UWB
    errors come from the same kinematics and error models as the other scenarios; all
    ``robots * (robots - 1) / 2`` pairs range, each with its own noise streams, so adding a
    robot does not change an existing pair's measurements. The arena is the grid's extent plus
    2 m on every side. No objects: detections see nothing here.
    """
    if robots < 2:
        raise ValueError(f"the grid needs at least 2 robots, got {robots}")
    cols = math.ceil(math.sqrt(robots))
    rows = math.ceil(robots / cols)
    cells = [
        ((k % cols - (cols - 1) / 2) * spacing, (k // cols - (rows - 1) / 2) * spacing)
        for k in range(robots)
    ]
    yaw0 = _initial_yaw(seed, "r0", heading_offsets)
    motions = [
        RobotMotion(
            "r0", "n_0", cells[0][0], cells[0][1], 0.0 if yaw0 is None else yaw0, pattern="static"
        )
    ]
    for i in range(1, robots):
        name = f"r{i}"
        radius, speed = (
            float(v) for v in stream(seed, "grid-circle", name).uniform((0.7, 0.2), (1.1, 0.3))
        )
        motions.append(
            looped_motion(
                name,
                f"n_{i}",
                "circle",
                circle_loop(cells[i][0], cells[i][1], radius, speed),
                seed=seed,
                duration=duration,
                initial_yaw=_initial_yaw(seed, name, heading_offsets),
                turn_rate=TURN_RATE,
                commanded=False,
            )
        )
    xs, ys = np.asarray(cells).T
    margin = 2.0
    area = (
        float(xs.min()) - margin,
        float(xs.max()) + margin,
        float(ys.min()) - margin,
        float(ys.max()) + margin,
    )
    return Simulation(
        motions,
        reference="r0",
        seed=seed,
        duration=duration,
        name=f"sim_grid{robots}",
        detections=detections,
        uwb=uwb,
        odometry=odometry,
        area=area,
    )


TAG_BASELINE = 0.3
"""Distance between the two tags of each robot of the ``tags`` scenarios (m)."""


def tags_scenario(seed: int = 0, *, odometry: bool = False, **options: Any) -> Simulation:
    """The multi team with two UWB tags on every robot, ``TAG_BASELINE`` apart (every two
    robots' tags ranging), without odometry (``tags``) or with it (``tags_odometry``)."""
    name = "sim_tags_odometry" if odometry else "sim_tags"
    return multi_scenario(seed, tags=TAG_BASELINE, odometry_topics=odometry, name=name, **options)


def tags_odometry_scenario(seed: int = 0, **options: Any) -> Simulation:
    """:func:`tags_scenario` with odometry."""
    return tags_scenario(seed, odometry=True, **options)


SCENARIOS: dict[str, Callable[..., Simulation]] = {
    "multi": multi_scenario,
    "tags": tags_scenario,
    "tags_odometry": tags_odometry_scenario,
    "single": single_scenario,
    "static": static_scenario,
    "static_then_move": static_then_move_scenario,
    "grid": grid_scenario,
    "drones": drones_scenario,
    "drones_uwb": drones_uwb_scenario,
    "drones_six": drones_six_scenario,
}
"""The open-loop scenarios by name, each called as ``scenario(seed, **options)`` (``nav`` is
closed-loop and run apart). ``static`` and ``static_then_move`` show how the estimate reports an
unobservable orientation; ``grid`` is the scaling scenario (``robots=N``); ``tags`` and
``tags_odometry`` give every robot two UWB tags; ``drones`` and ``drones_uwb`` are a flying team
in 3D, with and without odometry and heights (:mod:`relloc.simulator.flight`)."""
