"""Where a UWB driver's message keeps its ranges: the fields named in ``[uwb]``.

``sensor_msgs/msg/Range`` carries one range of one node pair per topic. Many UWB drivers
publish their own type instead, often one message per node listing every peer it ranged:
Nooploop LinkTrack's ``nlink_parser/msg/LinktrackNodeframe2`` has ``LinktrackNode2[] nodes``
with ``uint8 id`` and ``float32 dis`` per peer. A team config names the type
(``uwb.range_type``), the folders of its ``.msg`` files (``uwb.msg_dirs``) and two field paths:
``distance_field`` (``range``; ``nodes[].dis``) and, for a type listing peers, ``peer_field``
(``nodes[].id``). A path is dotted field names; one segment may end in ``[]`` (a sequence of
peers), and both paths then share it. :class:`RangeFields` checks the paths against the type's
definition before a run and reads them from decoded messages.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from relloc.config import ConfigError, UwbConfig
from relloc.ros.distros import layouts
from relloc.ros.stores import custom_types, register_types, store

__all__ = ["RangeFields", "load_range_type"]

_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4  # rosbags' node types of a field


def load_range_type(uwb: UwbConfig) -> None:
    """Register the ``.msg`` files of ``uwb.msg_dirs``; a ``range_type`` still unknown after
    that is a :class:`ConfigError` naming the type and the folders searched."""
    for folder in uwb.msg_dirs:
        path = Path(folder)
        if not path.is_dir():
            raise ConfigError(f"uwb.msg_dirs: {folder} is not a folder")
        types = custom_types(path)
        if types:
            register_types(types)
    if not layouts(uwb.range_type):
        searched = ", ".join(uwb.msg_dirs) or "none given"
        raise ConfigError(
            f"uwb.range_type {uwb.range_type!r}: no definition found (ROS 2 message types, relloc's "
            f"own and uwb.msg_dirs: {searched}; a folder holds <package>/msg/<Type>.msg)"
        )


@dataclass(frozen=True)
class RangeFields:
    """The distance (and peer id) paths of a range type, checked against its definition."""

    msgtype: str
    array: tuple[str, ...]
    """Path to the sequence of peers (empty: one range per message)."""
    distance: tuple[str, ...]
    """Path to the distance (m), inside each peer when ``array``."""
    peer: tuple[str, ...]
    """Path to the peer's node id inside each peer (empty: the topic names the pair)."""
    header: bool
    """Whether the type starts with a ``std_msgs/Header`` (else messages get receive times)."""

    @classmethod
    def of(cls, uwb: UwbConfig) -> RangeFields:
        """The fields of ``uwb`` (the type loaded: :func:`load_range_type`)."""
        msgtype = uwb.range_type
        array, distance = _split(uwb.distance_field, "distance_field")
        peer: tuple[str, ...] = ()
        if uwb.peer_field:
            peer_array, peer = _split(uwb.peer_field, "peer_field")
            if not array or peer_array != array:
                raise ConfigError(
                    f"uwb.peer_field {uwb.peer_field!r} and distance_field {uwb.distance_field!r} must "
                    "name fields of the same sequence of peers (e.g. nodes[].id and nodes[].dis)"
                )
        elif array:
            raise ConfigError(
                f"uwb.distance_field {uwb.distance_field!r} names a sequence: give peer_field too"
            )
        fielddefs = store().fielddefs
        inner = (
            _walk(fielddefs, msgtype, array, "sequence", uwb.distance_field) if array else msgtype
        )
        _walk(fielddefs, inner, distance, "number", uwb.distance_field)
        if peer:
            _walk(fielddefs, inner, peer, "id", uwb.peer_field)
        first = fielddefs[msgtype][1][0] if fielddefs[msgtype][1] else None
        header = first is not None and first[0] == "header" and first[1][1] == "std_msgs/msg/Header"
        return cls(msgtype, array, distance, peer, header)

    def ranges(self, msg: Any) -> Iterator[tuple[str, float]]:
        """``(peer node id, distance)`` of each peer of a message (``""`` as the id when the
        topic names the pair)."""
        if not self.array:
            yield "", float(_get(msg, self.distance))
            return
        for item in _get(msg, self.array):
            yield _node_id(_get(item, self.peer)), float(_get(item, self.distance))


def _split(spec: str, key: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``"nodes[].dis"`` -> ``(("nodes",), ("dis",))``; ``"range"`` -> ``((), ("range",))``."""
    parts = spec.split(".")
    if not spec or not all(p.removesuffix("[]").isidentifier() for p in parts):
        raise ConfigError(f"uwb.{key} {spec!r} is not a field path like 'range' or 'nodes[].dis'")
    marked = [i for i, p in enumerate(parts) if p.endswith("[]")]
    if len(marked) > 1 or (marked and marked[0] == len(parts) - 1):
        raise ConfigError(f"uwb.{key} {spec!r}: one sequence of peers, followed by a field in it")
    if not marked:
        return (), tuple(parts)
    cut = marked[0] + 1
    return tuple(p.removesuffix("[]") for p in parts[:cut]), tuple(parts[cut:])


def _walk(
    fielddefs: dict[str, Any], msgtype: str, path: tuple[str, ...], want: str, spec: str
) -> str:
    """Follow ``path`` in ``msgtype``'s definition: the element type of a ``sequence``, or
    checks that a ``number`` / ``id`` is a base type; raises a :class:`ConfigError` naming
    ``spec`` otherwise."""
    current = msgtype
    for i, name in enumerate(path):
        fields = dict(fielddefs[current][1])
        if name not in fields:
            raise ConfigError(
                f"uwb field {spec!r}: {current} has no field {name!r} (it has {sorted(fields)})"
            )
        nodetype, detail = int(fields[name][0]), fields[name][1]
        last = i == len(path) - 1
        if last and want == "sequence":
            if nodetype not in (_ARRAY, _SEQUENCE) or int(detail[0][0]) != _NAME:
                raise ConfigError(
                    f"uwb field {spec!r}: {current}.{name} is not a sequence of messages"
                )
            return str(detail[0][1])
        if last:
            ok = nodetype == _BASE and (
                want == "id" or detail[0] not in ("string", "wstring", "bool")
            )
            if not ok:
                raise ConfigError(f"uwb field {spec!r}: {current}.{name} is not a {want}")
            return current
        if nodetype != _NAME:
            raise ConfigError(f"uwb field {spec!r}: {current}.{name} is not a message")
        current = str(detail)
    return current


def _get(msg: Any, path: tuple[str, ...]) -> Any:
    for name in path:
        msg = getattr(msg, name)
    return msg


def _node_id(value: Any) -> str:
    """A peer id as the config spells node ids: integers without a fraction, strings as they are."""
    if isinstance(value, bytes):
        return value.decode(errors="replace")
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)
