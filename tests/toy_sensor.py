"""A sensor relloc has never heard of, defined outside ``src``: the plug-in of
``tests/test_plugin_sensor.py``.

A *toy fix* says where one robot is relative to the reference robot, in the shared heading
frame, with an isotropic Gaussian error: its own ROS message (``toy_msgs/msg/ToyFix``, in
``tests/plugin/msg``), its event, its measurement model and its descriptor, configured by a
``[sensors.toy_fix]`` table of the team config::

    [sensors.toy_fix]
    topic = "/{robot}/toy_fix"   # one topic per robot that has the sensor
    robots = ["r2"]
    sigma = 0.1                  # m, per axis
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from relloc.config import ConfigError, RobotConfig, TeamConfig
from relloc.filter.factors import RelativeFix
from relloc.filter.measurement import (
    LinearRow,
    MeasurementModel,
    ModelContext,
    ValidationContext,
    finite,
)
from relloc.filter.state import TeamLayout
from relloc.ros.messages import custom_types, time_msg, typestore
from relloc.sensors import Conversion, Route, Sensor, Switch

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

TOY_FIX = "toy_msgs/msg/ToyFix"
MSG_DIR = Path(__file__).resolve().parent / "plugin" / "msg"


@dataclass(frozen=True, slots=True)
class ToyFixEvent:
    """``robot`` is at ``(x, y)`` relative to the reference robot (shared heading frame, m)."""

    t: float
    robot: str
    x: float
    y: float
    sigma: float


@dataclass(frozen=True)
class ToyFixBatch(MeasurementModel):
    """``K`` toy fixes: a Gaussian of ``sigma`` per axis around each robot's relative position
    (the protocol's defaults for the hooks it does not define)."""

    events: ClassVar[tuple[type, ...]] = (ToyFixEvent,)
    stat: ClassVar[str] = "toy_fix"
    invariant: ClassVar[bool] = False
    needs_shared_heading: ClassVar[bool] = True
    conditions: ClassVar[bool] = False

    index: IntArray  # (K,)
    fix: FloatArray  # (K, 2)
    sigma: FloatArray  # (K,)
    layout: TeamLayout

    @classmethod
    def build(cls, events: Sequence[ToyFixEvent], context: ModelContext) -> list[MeasurementModel]:
        layout = context.layout
        return [
            cls(
                np.array([layout.index(e.robot) for e in events], dtype=np.intp),
                np.array([[e.x, e.y] for e in events]),
                np.array([e.sigma for e in events]),
                layout,
            )
        ]

    @classmethod
    def fixes(
        cls, events: Sequence[ToyFixEvent], context: ModelContext
    ) -> tuple[list[RelativeFix], int]:
        """For a factor graph: each fix a relative position from the reference."""
        layout = context.layout
        ref = layout.index(layout.reference)
        return [
            RelativeFix(ref, layout.index(e.robot), np.array([e.x, e.y]), e.sigma**2 * np.eye(2))
            for e in events
        ], 0

    @classmethod
    def heard(cls, event: ToyFixEvent) -> tuple[str, ...]:
        """A fix is news of where its robot is (the unseen-robot rule)."""
        return (event.robot,)

    @classmethod
    def rejection(cls, event: ToyFixEvent, context: ValidationContext) -> str | None:
        if event.robot not in context.layout.robots or event.robot == context.layout.reference:
            return "toy_fix_robot"
        if not all(map(finite, (event.x, event.y, event.sigma))) or event.sigma <= 0:
            return "toy_fix_invalid"
        return "late_measurement" if context.is_late(event.t) else None

    def log_likelihood(self, positions: FloatArray, particles: FloatArray) -> FloatArray:
        """Summed over the fixes, for every particle: ``(M,)``."""
        ex = positions[0, self.index] - self.fix[:, 0:1]
        ey = positions[1, self.index] - self.fix[:, 1:2]
        s2 = (self.sigma**2)[:, None]
        return (-0.5 * (ex * ex + ey * ey) / s2 - np.log(2.0 * math.pi * s2)).sum(axis=0)

    @property
    def rows(self) -> int:
        return 2 * len(self.sigma)

    def row(self, k: int, mean: FloatArray) -> LinearRow:
        j, axis = divmod(k, 2)
        col = 2 * self.layout.slot_of(int(self.index[j])) + axis
        n = mean.shape[0]
        return LinearRow(
            np.array([col]),
            np.ones((n, 1)),
            float(self.fix[j, axis]) - mean[:, col],
            float(self.sigma[j]) ** 2,
        )

    def condition(self, positions: FloatArray, particles: FloatArray) -> None:
        """No sufficient statistics in the state."""


@dataclass(frozen=True)
class ToySettings:
    """The parsed ``[sensors.toy_fix]`` table."""

    topic: str
    robots: tuple[str, ...]
    sigma: float


class ToyFixSensor(Sensor):
    """The toy fix as a relloc sensor: routes from its config table, decoding, replay."""

    kind: ClassVar[str] = "toy_fix"
    event: ClassVar[type] = ToyFixEvent
    msgtypes: ClassVar[tuple[str, ...]] = (TOY_FIX,)
    msg_types: ClassVar[Mapping[str, Any]] = custom_types(MSG_DIR)
    model = ToyFixBatch
    switch: ClassVar[Switch | None] = None
    wake: ClassVar[Literal["odometry", "measurement"] | None] = "measurement"

    def settings(self, config: TeamConfig) -> ToySettings | None:
        table = config.sensors.get(self.kind)
        if table is None:
            return None
        unknown = sorted(set(table) - {"topic", "robots", "sigma"})
        if unknown:
            raise ConfigError(
                f"sensors.{self.kind}: unknown key(s) {unknown}; known: ['robots', 'sigma', 'topic']"
            )
        topic, robots, sigma = (
            table.get("topic", ""),
            table.get("robots", []),
            table.get("sigma", 0.1),
        )
        if not isinstance(topic, str) or "{robot}" not in topic:
            raise ConfigError(
                f"sensors.{self.kind}.topic must be a string with {{robot}}, got {topic!r}"
            )
        if not isinstance(robots, list) or not set(robots) <= set(config.robot_names):
            raise ConfigError(
                f"sensors.{self.kind}.robots must name robots of {list(config.robot_names)}, got {robots!r}"
            )
        if isinstance(sigma, bool) or not isinstance(sigma, int | float) or not sigma > 0:
            raise ConfigError(f"sensors.{self.kind}.sigma must be a positive number, got {sigma!r}")
        return ToySettings(topic, tuple(robots), float(sigma))

    def robot_routes(self, config: TeamConfig, robot: RobotConfig) -> list[Route]:
        s = self.settings(config)
        if s is None or robot.name not in s.robots:
            return []
        return [
            Route(
                s.topic.format(robot=robot.name),
                self.kind,
                self.msgtypes,
                robot.name,
                f"toy fixes of {robot.name}",
                params=s.sigma,
            )
        ]

    def convert(
        self,
        route: Route,
        stream: str,
        msg: Any,
        fast: tuple[float, ...] | None,
        stamp: float,
        ingest: Conversion,
    ) -> ToyFixEvent:
        return ToyFixEvent(stamp, route.robot, float(msg.x), float(msg.y), route.params)

    def simulate(self, sim: Any, t0: float, t1: float) -> list[ToyFixEvent]:
        """Exact fixes at 2 Hz (on the half second) of the robots of ``sim.config``'s table."""
        s = self.settings(sim.config)
        if s is None:
            return []
        ticks = [0.5 * k for k in range(max(math.floor(2 * t0) + 1, 1), math.floor(2 * t1) + 1)]
        out = []
        for t in ticks:
            rx, ry, _ = sim.true_pose(sim.config.reference, t)
            for robot in s.robots:
                x, y, _ = sim.true_pose(robot, t)
                out.append(ToyFixEvent(t, robot, x - rx, y - ry, s.sigma))
        return out

    def message(self, event: ToyFixEvent) -> Any:
        types = typestore().types
        header = types["std_msgs/msg/Header"](stamp=time_msg(event.t), frame_id="")
        return types[TOY_FIX](header=header, x=event.x, y=event.y)


TOY = ToyFixSensor()
