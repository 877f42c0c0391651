"""Estimates out over Eclipse Zenoh, as ROS 2 messages a bridge or rmw_zenoh hands to ROS.

The derivation: docs/explanation/internals.md, section ``relloc.sinks.zenoh_sink``.
"""

from __future__ import annotations

import json
import logging
import time
from collections import Counter
from typing import Any

import numpy as np

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.ros.estimate_msgs import estimate_pose_cdr
from relloc.ros.interfaces import Channel, RosInterface
from relloc.ros.messages import POSE_WITH_COVARIANCE_STAMPED
from relloc.ros.zenoh_node import ZenohNode
from relloc.sources.zenoh_source import Arrival

__all__ = ["STRING", "ZenohSink", "pose_topic", "shape_message"]

log = logging.getLogger(__name__)

STRING = "std_msgs/msg/String"


def pose_topic(prefix: str, robot: str, method: str | None = None) -> str:
    """Topic of a robot's estimate: ``<prefix>/<robot>/pose``, or with ``<method>/`` inserted
    (its key is the interface's: :meth:`RosInterface.channel
    <relloc.ros.interfaces.RosInterface.channel>` with ``POSE_WITH_COVARIANCE_STAMPED``)."""
    parts = [prefix.strip("/"), method or "", robot, "pose"]
    return "/".join(p for p in parts if p)


class ZenohSink:
    """Engine sink publishing estimates (and status, and optionally traces) on a session.

    Call it with each :class:`~relloc.estimate.Estimate` (the engine does); call
    :meth:`set_trigger` before feeding an event so that traces can name it, and
    :meth:`publish_status` about once a second. :meth:`close` undeclares the publishers (the
    session belongs to the caller).
    """

    def __init__(
        self,
        session: Any,
        config: TeamConfig,
        *,
        interface: RosInterface | None = None,
        prefix: str = "relloc",
        primary_method: str = "pf",
        trace: bool = False,
    ) -> None:
        self.session = session
        self.config = config
        self.interface = iface = interface or RosInterface()
        self.node = ZenohNode(session, iface, "relloc")
        self.prefix = prefix.strip("/")
        self.primary_method = primary_method
        self.trace = trace
        self.published: Counter[str] = Counter()
        """Estimates published per method."""
        self.last: dict[str, Estimate] = {}
        """Last estimate published per method."""
        self._channels: dict[tuple[str, str], Channel] = {}
        self._trigger: Arrival | None = None
        self.status_channel = iface.channel(f"{self.prefix}/status", STRING)
        self.trace_channel = iface.channel(f"{self.prefix}/trace", STRING)
        self.status_key = self.status_channel.key
        self.trace_key = self.trace_channel.key

    def set_trigger(self, arrival: Arrival | None) -> None:
        """The message being fed now: estimates emitted while it is processed name it."""
        self._trigger = arrival

    def channel(self, robot: str, method: str) -> Channel:
        """The channel of ``robot``'s estimates by ``method``."""
        channel = self._channels.get((robot, method))
        if channel is None:
            topic = pose_topic(
                self.prefix, robot, None if method == self.primary_method else method
            )
            channel = self.interface.channel(topic, POSE_WITH_COVARIANCE_STAMPED)
            self._channels[(robot, method)] = channel
        return channel

    def shape_channel(self, method: str) -> Channel:
        """The channel of the shapes by ``method``: ``<prefix>/shape`` for the primary one."""
        channel = self._channels.get(("", method))
        if channel is None:
            parts = [self.prefix, "" if method == self.primary_method else method, "shape"]
            channel = self.interface.channel("/".join(p for p in parts if p), STRING)
            self._channels[("", method)] = channel
        return channel

    def shape_wanted(self, method: str) -> bool:
        """Whether anyone subscribes to the shapes by ``method`` (its publisher is declared
        here, so that Zenoh can tell): what the localizer then computes for them."""
        return self.node.publisher(self.shape_channel(method)).matching

    def key(self, robot: str, method: str) -> str:
        return self.channel(robot, method).key

    def __call__(self, estimate: Estimate) -> None:
        shown = estimate.published()  # once, not per robot
        for robot in shown.positions:  # the one conversion: relloc.ros.estimate_msgs
            payload = estimate_pose_cdr(shown, robot)
            self.node.put(self.channel(robot, estimate.method), payload)
        if estimate.shape:
            text = json.dumps(shape_message(estimate))
            self.node.put(self.shape_channel(estimate.method), self.interface.text_payload(text))
        self.published[estimate.method] += 1
        self.last[estimate.method] = estimate
        if self.trace:
            text = json.dumps(self._trace(estimate))
            self.node.put(self.trace_channel, self.interface.text_payload(text))

    def publish_status(self, status: dict[str, Any]) -> None:
        """Publish a status dict as JSON on ``<prefix>/status``."""
        text = json.dumps(status, default=_jsonable)
        self.node.put(self.status_channel, self.interface.text_payload(text))

    def close(self) -> None:
        """Undeclare the publishers and tokens (idempotent)."""
        self.node.close()

    def _trace(self, estimate: Estimate) -> dict[str, Any]:
        trig = self._trigger
        return {
            "method": estimate.method,
            "t": estimate.t,
            "trigger_key": trig.key if trig else None,
            "trigger_stamp": trig.event.t if trig else None,
            "trigger_sent": trig.sent if trig else None,
            "trigger_received": trig.received if trig else None,
            "published": time.time(),
        }


def shape_message(estimate: Estimate) -> dict[str, Any]:
    """What ``<prefix>/shape`` carries for ``estimate`` (see the module docstring)."""
    return {
        "t": estimate.t,
        "method": estimate.method,
        "reference": estimate.reference,
        "frame": estimate.frame,
        "orientation_observable": estimate.orientation_observable,
        "mode_weight": estimate.mode_weight,
        "n_modes": estimate.n_modes,
        "gauge": estimate.shape_gauge,
        "shape": {r: list(xy) for r, xy in estimate.shape.items()},
        "distances": {pair: list(d) for pair, d in estimate.distances.items()},
        "status": estimate.status,
    }


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Counter | set | frozenset | tuple):
        return list(value) if not isinstance(value, Counter) else dict(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
