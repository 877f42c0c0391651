"""A ROS 2 node made of Zenoh entities: publishers and subscriptions as either interface has them.

:class:`ZenohNode` is what every relloc process that talks to robots holds (server, replay,
simulated robots, navigation). It asks its :class:`~relloc.ros.interfaces.RosInterface` for the
keys and declares, on a Zenoh session it does not own:

* per :class:`~relloc.ros.interfaces.Channel` one Zenoh publisher (:class:`RosPublisher`), whose
  every ``put`` carries an attachment: relloc's send time on the bridge, the rmw_zenoh
  attachment (sequence number, source timestamp, the publisher's GID) with rmw_zenoh;
* subscriptions on the interface's subscription expression (with rmw_zenoh: any type hash);
* with rmw_zenoh, the liveliness tokens of the node (``NN``), of each publisher (``MP``) and of
  each subscription (``MS``), so that ``ros2 node list`` and ``ros2 topic list``/``info`` on an
  rmw_zenoh machine see relloc's node, topics and types.

Nothing is declared before it is needed, so a node can be built without a session (tests that
only look at keys). :meth:`ZenohNode.close` undeclares everything, tokens last.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import time
from collections.abc import Callable
from typing import Any

from relloc.ros.interfaces import Channel, RmwAttachment, RosInterface, encode_sent_time

__all__ = ["RosPublisher", "ZenohNode"]

log = logging.getLogger(__name__)

_NODE_IDS = itertools.count()
_ENTITY_IDS = itertools.count(10)  # unique within the process, so within each of its sessions


class RosPublisher:
    """One Zenoh publisher of a :class:`~relloc.ros.interfaces.Channel`."""

    def __init__(self, publisher: Any, channel: Channel, gid: bytes | None) -> None:
        self.publisher = publisher
        self.channel = channel
        self.gid = gid
        """The 16-byte GID (rmw_zenoh), ``None`` on the bridge."""
        self._sequence = itertools.count(1)
        self.sent = 0

    def put(self, payload: bytes) -> None:
        """Publish ``payload`` (serialised CDR, or text) with the interface's attachment."""
        now = time.time_ns()
        if self.gid is None:
            attachment = encode_sent_time(now * 1e-9)
        else:
            attachment = RmwAttachment(next(self._sequence), now, self.gid).encode()
        self.publisher.put(payload, attachment=attachment)
        self.sent += 1

    @property
    def matching(self) -> bool:
        """Whether some subscriber matches the key."""
        return bool(self.publisher.matching_status.matching)

    def undeclare(self) -> None:
        self.publisher.undeclare()


class ZenohNode:
    """A node named ``name`` (in ``namespace``) on ``session`` speaking ``interface``."""

    def __init__(
        self, session: Any, interface: RosInterface, name: str, *, namespace: str = ""
    ) -> None:
        self.session = session
        self.interface = interface
        self.name = name
        self.namespace = namespace
        self.node_id = next(_NODE_IDS)
        self._publishers: dict[str, RosPublisher] = {}
        self._subscribers: list[Any] = []
        self._tokens: list[Any] = []
        self._session_id: str | None = None
        self.tokens: list[str] = []
        """Keys of the liveliness tokens declared (rmw_zenoh)."""

    # ------------------------------------------------------------------ entities
    def publisher(self, channel: Channel) -> RosPublisher:
        """The publisher of ``channel`` (declared on first use, with its ``MP`` token)."""
        pub = self._publishers.get(channel.key)
        if pub is None:
            gid = None
            if self.interface.rmw:
                token = self._declare_endpoint("MP", channel)
                gid = hashlib.sha256(token.encode()).digest()[:16]
            pub = RosPublisher(self.session.declare_publisher(channel.key), channel, gid)
            self._publishers[channel.key] = pub
        return pub

    def put(self, channel: Channel, payload: bytes) -> None:
        self.publisher(channel).put(payload)

    def subscribe(self, channel: Channel, callback: Callable[[Any], None]) -> Any:
        """Subscribe ``callback`` (called on Zenoh's threads with each sample) to the samples of
        ``channel``'s topic, whatever their type hash with rmw_zenoh (an ``MS`` token is declared)."""
        if self.interface.rmw:
            self._declare_endpoint("MS", channel)
        sub = self.session.declare_subscriber(
            self.interface.subscription_expr(channel.topic_key), callback
        )
        self._subscribers.append(sub)
        return sub

    def announce_subscription(self, channel: Channel) -> None:
        """Declare (rmw_zenoh) the ``MS`` token of a subscription made elsewhere on the session
        (the live source's own subscribers), so that the ROS graph lists it."""
        if self.interface.rmw:
            self._declare_endpoint("MS", channel)

    def wait_matching(
        self, channels: list[Channel], timeout: float, stop: Callable[[], bool] = lambda: False
    ) -> list[str]:
        """Wait until every channel has a subscriber (or ``timeout``); returns the keys of those
        still without."""
        pending = list({c.key: c for c in channels}.values())
        end = time.time() + timeout
        while pending and time.time() < end and not stop():
            pending = [c for c in pending if not self.publisher(c).matching]
            if pending:
                time.sleep(0.02)
        return [c.key for c in pending]

    @property
    def publishers(self) -> dict[str, RosPublisher]:
        return dict(self._publishers)

    def close(self) -> None:
        """Undeclare publishers, subscribers and tokens (idempotent; the session stays open)."""
        pubs, self._publishers = self._publishers, {}
        subs, self._subscribers = self._subscribers, []
        tokens, self._tokens = self._tokens, []
        for entity in [*pubs.values(), *subs, *reversed(tokens)]:
            try:
                entity.undeclare()
            except Exception as exc:  # the session may already be closed
                log.debug("undeclaring %r failed: %s", entity, exc)

    # ------------------------------------------------------------------ liveliness
    def _declare_endpoint(self, kind: str, channel: Channel) -> str:
        session_id = self._node_session_id()
        token = self.interface.endpoint_token(
            session_id, self.node_id, next(_ENTITY_IDS), kind, self.name, channel,
            namespace=self.namespace,
        )  # fmt: skip
        self._declare_token(token)
        return token

    def _node_session_id(self) -> str:
        if self._session_id is None:
            self._session_id = str(self.session.zid())
            self._declare_token(
                self.interface.node_token(self._session_id, self.node_id, self.name, self.namespace)
            )
        return self._session_id

    def _declare_token(self, key: str) -> None:
        self._tokens.append(self.session.liveliness().declare_token(key))
        self.tokens.append(key)
