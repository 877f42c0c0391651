"""Faults injected into ROS 2 messages on their way out (``relloc replay --drop ...``).

:mod:`relloc.faults` transforms relloc events. A replay publishes a bag's raw CDR messages, so
here each message of a team topic whose sensor can be faulted (odometry, UWB ranges, motion
capture, detections: :meth:`~relloc.sensors.Sensor.fault_event`) is decoded, turned into its
event as the ingestion layer would, put through the same :class:`~relloc.faults.FaultInjector`,
and, if the fault changed it, the changed fields are written back into the decoded message
(:meth:`~relloc.sensors.Sensor.write_back`) and it is encoded again; every other
field (covariances, twist, frame ids) is kept. A message the fault leaves alone goes out as the
very bytes of the bag, and a topic that is not the team's is never touched.

Times are the stream's: a message's header stamp. A topic recorded with zero stamps (restamped
on arrival by the server, ``odom_zero_stamps``) is timed by its receive time plus the offset of
the stamped topics seen so far, and a stamp fault leaves its zero stamp alone (the server would
restamp it anyway). A kidnapping needs the robots' ground truth: motion-capture messages go
through the injector even when they are not published.
"""

from __future__ import annotations

import dataclasses
import statistics
from collections import deque
from typing import Any

from relloc.config import TeamConfig
from relloc.events import Event
from relloc.faults import FaultInjector, Faults
from relloc.ros.messages import decode, encode, stamp_to_sec, time_msg
from relloc.sensors import Route, Sensor, sensor
from relloc.sources.ingest import team_routes

__all__ = ["MessageFaults"]

_OFFSETS = 50
"""Stamped messages whose (stamp - receive time) median times the zero-stamp topics."""


class MessageFaults:
    """``faults(topic, msgtype, raw, received)``: the payload to publish, or ``None`` if the
    message is lost (module docstring). ``counts`` says what was done (``dropped``,
    ``silenced``, ``shifted``, ``changed``)."""

    def __init__(self, config: TeamConfig, faults: Faults) -> None:
        self.injector = FaultInjector(faults)
        self.routes: dict[str, Route] = {}
        """The team's topics whose sensor is ``faulted``."""
        for r in team_routes(config, ground_truth=True):
            own = sensor(r.kind)
            if own.faulted and own.writes(r):
                self.routes[r.topic] = r
        self._offsets: deque[float] = deque(maxlen=_OFFSETS)

    @property
    def counts(self) -> dict[str, int]:
        return self.injector.counts

    def topics(self) -> set[str]:
        """The topics this transform reads (the team's; motion capture among them)."""
        return set(self.routes)

    def __call__(self, topic: str, msgtype: str, raw: bytes, received: float) -> bytes | None:
        route = self.routes.get(topic)
        if route is None:
            return raw
        msg = decode(raw, msgtype)
        stamp = stamp_to_sec(msg.header.stamp)
        zero = stamp == 0.0 or route.restamped
        if zero:
            t = received + (statistics.median(self._offsets) if self._offsets else 0.0)
        else:
            t = stamp
            self._offsets.append(stamp - received)
        own = sensor(route.kind)
        event = own.fault_event(route, msg, t)
        out = self.injector(event)
        if out is None:
            return None
        if out == event:
            return raw
        self.counts["changed"] = self.counts.get("changed", 0) + 1
        return encode(_written_back(own, msg, event, out, zero), msgtype)


def _written_back(own: Sensor, msg: Any, before: Event, after: Event, zero_stamp: bool) -> Any:
    """``msg`` with the fields the fault changed (``before`` -> ``after``) set to their new
    values: the stamp here, the rest by the sensor (:meth:`~relloc.sensors.Sensor.write_back`)."""
    if after.t != before.t and not zero_stamp:
        msg = dataclasses.replace(
            msg, header=dataclasses.replace(msg.header, stamp=time_msg(after.t))
        )
    return own.write_back(msg, before, after)
