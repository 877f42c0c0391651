"""The rmw_zenoh envelope of a sample: its type name and hash in the key, its attachment.

With ``rmw_zenoh`` every sample's key names its message type and that type's hash, and its
attachment carries the publisher's GID, a sequence number and the source timestamp.
:class:`RmwEnvelope` checks the type against the route's, picks the layout the hash names
(:func:`relloc.ros.distros.layout_of_hash`; ``TypeHashNotSupported`` from a Humble node or an
unknown hash: none, and the decoder tries each known layout), and reads the attachment,
counting what it finds in :class:`TransportStats` (never fatal: only a type the route does not
take drops the sample).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from relloc.ros.distros import HASH_NOT_SUPPORTED, Layout, layout_of_hash
from relloc.ros.interfaces import RmwAttachment, ros_type_name

__all__ = ["RmwEnvelope", "TransportStats"]

log = logging.getLogger(__name__)


@dataclass
class TransportStats:
    """What the interface's own envelope of the messages told (counted, never fatal).

    With rmw_zenoh: samples without the attachment or with a malformed one (the message is
    still used; only latency and loss cannot be known for it), samples whose key names a type
    the topic's route does not take (dropped, and also counted as the rejection
    ``unknown_type``), samples by how their layout was chosen (``layout_by_hash``; without a
    usable hash every known layout is tried: ``hash_not_supported`` from Humble nodes,
    ``unknown_type_hash`` per ``<type name>/<hash>``; a payload no layout fits is a
    ``decode_error``), and samples lost: gaps in a publisher's sequence numbers.
    """

    attachment_missing: int = 0
    attachment_malformed: int = 0
    layout_by_hash: int = 0
    """Samples whose hash named a known layout."""
    hash_not_supported: int = 0
    """Samples keyed ``TypeHashNotSupported`` (rmw_zenoh for Humble)."""
    unknown_type_hash: Counter[str] = field(default_factory=Counter)
    """Per ``<type name>/<hash>`` seen."""
    lost: Counter[str] = field(default_factory=Counter)
    """Samples missing from the sequence numbers, per topic key."""
    sequence_restarts: int = 0
    """A publisher's sequence number went back (it restarted, or duplicates)."""
    publishers: int = 0
    """Distinct publisher GIDs seen."""

    def as_dict(self) -> dict[str, Any]:
        return {
            "attachment_missing": self.attachment_missing,
            "attachment_malformed": self.attachment_malformed,
            "layout_by_hash": self.layout_by_hash,
            "hash_not_supported": self.hash_not_supported,
            "unknown_type_hash": dict(self.unknown_type_hash),
            "lost": dict(self.lost),
            "sequence_restarts": self.sequence_restarts,
            "publishers": self.publishers,
        }


class RmwEnvelope:
    """Checks rmw_zenoh samples against ``dds_types`` (per topic key, DDS type name -> ROS
    type name) and counts in :attr:`stats`."""

    def __init__(self, dds_types: dict[str, dict[str, str]]) -> None:
        self.dds_types = dds_types
        self.stats = TransportStats()
        self._last_sequence: dict[bytes, int] = {}

    def open(
        self,
        topic_key: str,
        dds_type: str | None,
        hash_: str | None,
        attachment: bytes | None,
        reject: Callable[[str, str, str], None],
    ) -> tuple[float | None, Layout | None] | None:
        """Check an rmw_zenoh sample's type and read its attachment: ``(source timestamp or
        None without a usable attachment, the layout its hash names or None)``, or ``None`` if
        the sample is to be dropped (``reject`` gets the reason, the key and a detail)."""
        expected = self.dds_types[topic_key]
        msgtype = expected.get(dds_type or "")
        if msgtype is None:
            name = ros_type_name(dds_type or "") or dds_type
            reject("unknown_type", topic_key, f"type {name!r}")
            return None
        tr = self.stats
        layout = layout_of_hash(msgtype, hash_)
        if layout is not None:
            tr.layout_by_hash += 1
        elif hash_ == HASH_NOT_SUPPORTED:
            tr.hash_not_supported += 1
        else:
            tr.unknown_type_hash[f"{dds_type}/{hash_}"] += 1
            n = tr.unknown_type_hash.total()
            if n == 1 or n % 1000 == 0:
                log.warning(
                    "%s: type hash %s is of no layout of %s relloc knows (%d so far); "
                    "trying each known layout",
                    topic_key, hash_, msgtype, n,
                )  # fmt: skip
        return self._sent(topic_key, attachment), layout

    def _sent(self, topic_key: str, attachment: bytes | None) -> float | None:
        """The source timestamp of an attachment (counting its sequence number), or ``None``."""
        tr = self.stats
        if attachment is None:
            tr.attachment_missing += 1
            if tr.attachment_missing == 1:
                log.warning("%s: a sample without the rmw_zenoh attachment", topic_key)
            return None
        try:
            att = RmwAttachment.decode(attachment)
        except ValueError as exc:
            tr.attachment_malformed += 1
            if tr.attachment_malformed == 1 or tr.attachment_malformed % 1000 == 0:
                log.warning(
                    "%s: malformed rmw_zenoh attachment (%s; %d so far)",
                    topic_key, exc, tr.attachment_malformed,
                )  # fmt: skip
            return None
        last = self._last_sequence.get(att.gid)
        if last is None:
            tr.publishers += 1
        elif att.sequence > last + 1:
            tr.lost[topic_key] += att.sequence - last - 1
        elif att.sequence <= last:
            tr.sequence_restarts += 1
        self._last_sequence[att.gid] = att.sequence
        return att.timestamp
