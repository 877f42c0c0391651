"""The height sensor: a robot's downward range finder (``height_topic``) -> :class:`HeightEvent`.

A flying robot's height above the ground fixes what UWB ranges between robots cannot: which
way is up, and each robot's height over the reference (the ``smoother3d`` kind fuses it; a 2D
kind counts it as ignored). The sensor publishes ``sensor_msgs/msg/Range`` pointing down;
the body origin's height is its ``range`` plus the robot's ``height_offset``, with the robot's
``height_sigma`` as noise.

A reading outside the message's own ``[min_range, max_range]`` (REP 117: a driver reports
"nothing in range" that way) or not finite is dropped and counted
(``height_out_of_range``, ``height_nonfinite``). Limits both 0 mean "not given" (how
:func:`~relloc.ros.messages.range_msg` writes a UWB range): then any reading ``>= 0`` passes.
"""

from __future__ import annotations

import math
import struct
from typing import Any, ClassVar, Literal

from relloc.config import RobotConfig, TeamConfig
from relloc.events import Event, HeightEvent
from relloc.ros.cdr import decode_range
from relloc.ros.distros import Layout
from relloc.ros.messages import RANGE, time_msg, typestore
from relloc.sensors.base import Conversion, Route, Sensor

__all__ = ["HEIGHT_SENSOR", "MESSAGE_MAX_RANGE", "Height", "height_rejection"]

_LIMITS = {e: struct.Struct(e + "2f") for e in "<>"}
"""``min_range, max_range``: the second and third of the four floats ending a Range message
(``field_of_view, min_range, max_range, range``, then ``variance`` since Iron)."""

MESSAGE_MAX_RANGE = 100.0
"""The ``max_range`` (m) of the messages :meth:`Height.message` writes (``min_range`` 0): wide
enough for any simulated flight, so a simulated height is only dropped below the ground."""


def height_rejection(value: float, min_range: float, max_range: float) -> str | None:
    """Why a range finder's reading is unusable (``"nonfinite"``, ``"out_of_range"``), or
    ``None``. Limits both 0 are "not given": a reading must then only be ``>= 0``."""
    if not math.isfinite(value):
        return "nonfinite"
    if min_range == max_range == 0.0:
        return None if value >= 0.0 else "out_of_range"
    return None if min_range <= value <= max_range else "out_of_range"


class Height(Sensor):
    """Each robot's ``height_topic``: ``sensor_msgs/msg/Range`` -> :class:`HeightEvent` with
    ``z = range + height_offset`` and ``sigma = height_sigma`` (module docstring)."""

    kind: ClassVar[str] = "height"
    event: ClassVar[type] = HeightEvent
    msgtypes: ClassVar[tuple[str, ...]] = (RANGE,)
    wake: ClassVar[Literal["odometry", "measurement"] | None] = None
    """Every height wakes a live engine: a few per second per robot, and a rule written for
    odometry and ranges need not say when a height may wait."""

    def robot_routes(self, config: TeamConfig, robot: RobotConfig) -> list[Route]:
        if not robot.height_topic:
            return []
        return [
            Route(
                robot.height_topic,
                self.kind,
                (RANGE,),
                robot.name,
                f"height of {robot.name}",
                params=(robot.height_offset, robot.height_sigma),
            )
        ]

    def fast(self, payload: bytes, layout: Layout) -> tuple[float, ...] | None:
        """``(stamp, range, min_range, max_range)``: :func:`~relloc.ros.cdr.decode_range`
        checks the layout and reads the range; the limits sit just before it."""
        if layout.msgtype != RANGE:
            return None
        variance = "variance" in layout.fields
        found = decode_range(payload, variance)
        if found is None:
            return None
        endian = "<" if payload[1] == 1 else ">"
        lo, hi = _LIMITS[endian].unpack_from(payload, len(payload) - (16 if variance else 12))
        return (*found, lo, hi)

    def convert(
        self,
        route: Route,
        stream: str,
        msg: Any,
        fast: tuple[float, ...] | None,
        stamp: float,
        ingest: Conversion,
    ) -> Event | None:
        if fast is not None:
            _, value, lo, hi = fast
        else:
            value, lo, hi = float(msg.range), float(msg.min_range), float(msg.max_range)
        reason = height_rejection(value, lo, hi)
        if reason is not None:
            ingest.reject(f"height_{reason}", stream, f"range {value!r} in [{lo!r}, {hi!r}]")
            return None
        offset, sigma = route.params
        return HeightEvent(t=stamp, robot=route.robot, z=value + offset, sigma=sigma)

    def message(self, event: HeightEvent) -> Any:
        """The height as the range finder's message, for a sensor at the body origin
        (``height_offset`` 0: the simulated robots'; the event does not say the offset):
        ``range = z``, limits ``[0, MESSAGE_MAX_RANGE]``, since Iron ``variance = sigma^2``
        (the reader takes the noise from the config: drivers often write 0, "unknown")."""
        types = typestore().types
        msg = types[RANGE]
        extra = (
            {"variance": event.sigma**2}
            if "variance" in getattr(msg, "__dataclass_fields__", {})
            else {}
        )
        header = types["std_msgs/msg/Header"](stamp=time_msg(event.t), frame_id="")
        return msg(
            header=header,
            radiation_type=1,  # INFRARED: a laser range finder
            field_of_view=0.0,
            min_range=0.0,
            max_range=MESSAGE_MAX_RANGE,
            range=float(event.z),
            **extra,
        )


HEIGHT_SENSOR = Height()
