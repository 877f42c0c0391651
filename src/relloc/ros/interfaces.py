"""How ROS 2 topics appear on Zenoh: the two interfaces relloc speaks, and their key formats.

This module is the one place that knows the keys: the source, the sink and the publishers of
``relloc replay``, ``relloc sim-robots`` and ``relloc navigate`` all ask a
:class:`RosInterface` for them, so the two conventions cannot drift apart.

``bridge`` (zenoh-bridge-ros2dds, the default)
    Each topic on the key named after it, the leading slash dropped (:func:`key_for_topic`);
    payloads are CDR bytes; relloc's publishers attach their send time
    (:func:`encode_sent_time`).

``rmw_zenoh`` (rmw_zenoh_cpp)
    Data keys ``<domain_id>/<topic>/<type name>/<type hash>`` (:func:`dds_type_name`), a
    33-byte attachment per sample (:class:`RmwAttachment`) and liveliness tokens; relloc
    subscribes to ``<domain>/<topic>/*/*`` and picks each sample's layout from its hash.

A topic is identified by its *topic key* (:meth:`RosInterface.topic_key`): the data key
without type name and hash; sources count messages per topic key. The key formats in full:
``docs/explanation/internals.md``.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Final

from relloc.config import ConfigError, RosDistro, RosInterfaceKind
from relloc.ros.distros import key_hash
from relloc.ros.stores import DEFAULT_DISTRO, check_distro

__all__ = [
    "BRIDGE",
    "DEFAULT_QOS",
    "RMW_ZENOH",
    "ROS_INTERFACES",
    "SENT_TIME_TAG",
    "Channel",
    "RmwAttachment",
    "RosInterface",
    "dds_type_name",
    "decode_sent_time",
    "encode_sent_time",
    "key_for_topic",
    "mangle",
    "ros_name",
    "ros_type_name",
]

BRIDGE: Final = "bridge"
RMW_ZENOH: Final = "rmw_zenoh"
ROS_INTERFACES: Final = (BRIDGE, RMW_ZENOH)

LIVELINESS_PREFIX: Final = "@ros2_lv"
DEFAULT_QOS: Final = "::,10:,:,:,,"
"""The QoS part of a liveliness token for relloc's endpoints: reliable, volatile, keep last 10,
no deadline, lifespan or liveliness lease (rmw_zenoh leaves default values empty and writes the
history depth: ``listener`` in the design document has ``::,10:,:,:,,``)."""

SENT_TIME_TAG = b"rlst"
"""Prefix of the 12-byte bridge-mode attachment ``rlst`` + float64 (little endian) send wall
time that relloc's publishers put on every message, so that end-to-end latency can be measured."""


def encode_sent_time(t: float) -> bytes:
    """The bridge-mode attachment carrying a publisher's send wall time (s since the epoch)."""
    return SENT_TIME_TAG + struct.pack("<d", t)


def decode_sent_time(attachment: bytes | None) -> float | None:
    """The send wall time of an attachment made by :func:`encode_sent_time`, else ``None``."""
    if attachment is None or len(attachment) != 12 or not attachment.startswith(SENT_TIME_TAG):
        return None
    return float(struct.unpack_from("<d", attachment, 4)[0])


_ATTACHMENT = struct.Struct("<qqB16s")


@dataclass(frozen=True, slots=True)
class RmwAttachment:
    """The attachment of every rmw_zenoh sample: ``<qqB16s>``, 33 bytes."""

    sequence: int
    """The publisher's sequence number: 1 for its first sample, then +1 per sample."""
    timestamp_ns: int
    """Source timestamp: the publisher's wall clock at publication, ns since the epoch."""
    gid: bytes
    """The publisher's 16-byte GID."""

    def encode(self) -> bytes:
        return _ATTACHMENT.pack(self.sequence, self.timestamp_ns, len(self.gid), self.gid)

    @classmethod
    def decode(cls, raw: bytes) -> RmwAttachment:
        """Raises ``ValueError`` unless ``raw`` is exactly a well-formed attachment."""
        if len(raw) != _ATTACHMENT.size:
            raise ValueError(
                f"an rmw_zenoh attachment has {_ATTACHMENT.size} bytes, not {len(raw)}"
            )
        sequence, stamp, n, gid = _ATTACHMENT.unpack(raw)
        if n != 16:
            raise ValueError(f"GID length {n}, expected 16")
        return cls(sequence, stamp, gid)

    @property
    def timestamp(self) -> float:
        """The source timestamp in s since the epoch."""
        return self.timestamp_ns * 1e-9


def key_for_topic(topic: str, *, prefix: str = "", scope: str = "") -> str:
    """The bridge-convention key of a ROS topic.

    ``key_for_topic("/tb1/odom") == "tb1/odom"``; ``prefix`` (global) and ``scope`` (the robot's
    ``zenoh_scope``) are prepended in that order: ``key_for_topic("/odom", prefix="lab",
    scope="tb1") == "lab/tb1/odom"``.
    """
    parts = [p.strip("/") for p in (prefix, scope, topic)]
    key = "/".join(p for p in parts if p)
    if not key or any(c in key for c in "*$?#@") or "//" in key:
        raise ConfigError(
            f"topic {topic!r} (prefix {prefix!r}, scope {scope!r}) is not a valid key"
        )
    return key


def ros_name(topic: str, scope: str = "") -> str:
    """The fully qualified ROS name of ``topic`` below the namespace ``scope``:
    ``ros_name("odom", "tb1") == "/tb1/odom"``."""
    return "/" + key_for_topic(topic, scope=scope)


def mangle(name: str) -> str:
    """A ROS name as one liveliness-token chunk: ``/`` -> ``%``; empty or ``/`` -> ``%``."""
    return name.replace("/", "%") if name.strip("/") else "%"


def dds_type_name(msgtype: str) -> str:
    """``"nav_msgs/msg/Odometry"`` -> ``"nav_msgs::msg::dds_::Odometry_"`` (the CDR type name)."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds_name: str) -> str | None:
    """The inverse of :func:`dds_type_name`, or ``None`` if ``dds_name`` is not of that form."""
    parts = dds_name.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_") or len(parts[3]) < 2:
        return None
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


@dataclass(frozen=True, slots=True)
class Channel:
    """One topic with one message type, as published: everything an endpoint needs."""

    key: str
    """The data key samples are put on."""
    topic_key: str
    """The data key without type name and hash (equal to ``key`` on the bridge)."""
    name: str
    """The fully qualified ROS topic name (``/tb1/odom``)."""
    msgtype: str
    """``pkg/msg/Name``."""
    distro: str = DEFAULT_DISTRO
    """The ROS 2 distribution whose layout of ``msgtype`` its payloads have."""


@dataclass(frozen=True)
class RosInterface:
    """Key formats, attachments and liveliness tokens of one interface (``bridge`` or
    ``rmw_zenoh``) on one ROS domain, for robots of one ROS 2 distribution."""

    kind: RosInterfaceKind = BRIDGE
    domain_id: int = 0
    """``ROS_DOMAIN_ID`` (rmw_zenoh only: the first chunk of every key)."""
    distro: RosDistro = DEFAULT_DISTRO
    """The robots' ROS 2 distribution: the layouts relloc publishes and, with rmw_zenoh, the
    type hashes of its keys and tokens (:mod:`relloc.ros.distros`)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "distro", check_distro(self.distro))
        if self.kind not in ROS_INTERFACES:
            raise ConfigError(f"ros_interface must be one of {ROS_INTERFACES}, got {self.kind!r}")
        if (
            isinstance(self.domain_id, bool)
            or not isinstance(self.domain_id, int)
            or self.domain_id < 0
        ):
            raise ConfigError(
                f"the ROS domain id must be a non-negative integer, got {self.domain_id!r}"
            )

    @property
    def rmw(self) -> bool:
        return self.kind == RMW_ZENOH

    # ------------------------------------------------------------------ data keys
    def topic_key(self, topic: str, *, prefix: str = "", scope: str = "") -> str:
        """The key of ``topic`` (below the namespace ``scope`` and the key prefix ``prefix``)
        without type name and hash: ``tb1/odom`` (bridge), ``0/tb1/odom`` (rmw_zenoh)."""
        if not self.rmw:
            return key_for_topic(topic, prefix=prefix, scope=scope)
        name = key_for_topic(topic, scope=scope)
        head = prefix.strip("/")
        return f"{head}/{self.domain_id}/{name}" if head else f"{self.domain_id}/{name}"

    def channel(self, topic: str, msgtype: str, *, prefix: str = "", scope: str = "") -> Channel:
        """The :class:`Channel` of ``topic`` carrying ``msgtype``."""
        topic_key = self.topic_key(topic, prefix=prefix, scope=scope)
        key = topic_key
        if self.rmw:
            key = f"{topic_key}/{dds_type_name(msgtype)}/{key_hash(msgtype, self.distro)}"
        return Channel(key, topic_key, ros_name(topic, scope), msgtype, self.distro)

    def subscription_expr(self, topic_key: str) -> str:
        """The key expression receiving a topic's samples: the topic key itself on the bridge,
        ``<topic key>/*/*`` (any type name, any hash) with rmw_zenoh."""
        return f"{topic_key}/*/*" if self.rmw else topic_key

    def everything_expr(self, prefix: str = "") -> str:
        """A key expression for every topic below ``prefix`` (on this domain)."""
        head = prefix.strip("/")
        if self.rmw:
            head = f"{head}/{self.domain_id}" if head else str(self.domain_id)
        return f"{head}/**" if head else "**"

    def split_key(self, key: str) -> tuple[str, str | None, str | None]:
        """A received data key as ``(topic key, DDS type name, type hash)``; the last two are
        ``None`` on the bridge and for an rmw_zenoh key too short to have them."""
        if not self.rmw:
            return key, None, None
        parts = key.rsplit("/", 2)
        if len(parts) != 3:
            return key, None, None
        return parts[0], parts[1], parts[2]

    # ------------------------------------------------------------------ text payloads
    def text_payload(self, text: str) -> bytes:
        """A text (relloc's JSON status) as published: UTF-8 on the bridge (a plain Zenoh key),
        a ``std_msgs/msg/String`` with rmw_zenoh (a ROS topic ``ros2 topic echo`` shows)."""
        if not self.rmw:
            return text.encode()
        data = text.encode() + b"\x00"
        return b"\x00\x01\x00\x00" + struct.pack("<I", len(data)) + data

    def decode_text(self, payload: bytes) -> str:
        """The inverse of :meth:`text_payload` (``ValueError`` on a malformed payload)."""
        if not self.rmw:
            return payload.decode()
        from relloc.ros.messages import decode

        return str(decode(payload, "std_msgs/msg/String").data)

    def decode_json(self, payload: bytes) -> object:
        return json.loads(self.decode_text(payload))

    # ------------------------------------------------------------------ liveliness tokens
    def node_token(self, session_id: str, node_id: int, node: str, namespace: str = "") -> str:
        """The liveliness token of a node (rmw_zenoh)."""
        return (
            f"{LIVELINESS_PREFIX}/{self.domain_id}/{session_id}/{node_id}/{node_id}/NN/%/"
            f"{mangle(namespace)}/{node}"
        )

    def endpoint_token(
        self,
        session_id: str,
        node_id: int,
        entity_id: int,
        kind: str,
        node: str,
        channel: Channel,
        *,
        namespace: str = "",
        qos: str = DEFAULT_QOS,
    ) -> str:
        """The liveliness token of a publisher (``kind="MP"``) or subscription (``"MS"``)."""
        if kind not in ("MP", "MS"):
            raise ValueError(f"endpoint kind must be MP or MS, got {kind!r}")
        return (
            f"{LIVELINESS_PREFIX}/{self.domain_id}/{session_id}/{node_id}/{entity_id}/{kind}/%/"
            f"{mangle(namespace)}/{node}/{mangle(channel.name)}/{dds_type_name(channel.msgtype)}/"
            f"{key_hash(channel.msgtype, channel.distro)}/{qos}"
        )

    def liveliness_expr(self) -> str:
        """Every liveliness token of this domain."""
        return f"{LIVELINESS_PREFIX}/{self.domain_id}/**"
