"""Sensors as plug-ins: one descriptor per kind of sensor, registered once.

A :class:`Sensor` (:mod:`relloc.sensors.base`) bundles a sensor's event type, its ROS message
types with decoder, fast path and replay encoder, its routes from the team config, its
measurement model, its counters and its fault hooks; ingestion, bag resolution, replay
encoding, message faults and the Zenoh source ask the :mod:`~relloc.sensors.registry` instead
of comparing kind names. The built-in sensors (:mod:`relloc.sensors.builtin`, and the range
finder's heights, :mod:`relloc.sensors.height`) are registered here; a new sensor is one
descriptor and one :func:`register` call (``docs/howto/extending.md``).
"""

from relloc.sensors.base import Conversion, Route, Sensor, Switch
from relloc.sensors.builtin import DETECTION, GROUND_TRUTH, ODOMETRY_SENSOR, RANGE_SENSOR, SIGHTING
from relloc.sensors.height import HEIGHT_SENSOR
from relloc.sensors.registry import (
    check_config,
    kind_of,
    register,
    registered,
    sensor,
    sensor_of,
    unregister,
)

__all__ = [
    "DETECTION",
    "GROUND_TRUTH",
    "HEIGHT_SENSOR",
    "ODOMETRY_SENSOR",
    "RANGE_SENSOR",
    "SIGHTING",
    "Conversion",
    "Route",
    "Sensor",
    "Switch",
    "check_config",
    "kind_of",
    "register",
    "registered",
    "sensor",
    "sensor_of",
    "unregister",
]

for _builtin in (ODOMETRY_SENSOR, SIGHTING, GROUND_TRUTH, DETECTION, RANGE_SENSOR, HEIGHT_SENSOR):
    register(_builtin)
