"""ROS 2 type hashes (RIHS01, REP 2011) computed from the message definitions relloc knows.

Since Iron, every ROS 2 message type has a *type hash*: ``RIHS01_`` followed by the hex SHA-256
of a canonical JSON form of the type's description. rmw_zenoh puts it in every data key and
liveliness token, so a publisher whose hash differs from the subscriber's is never matched; to
be heard by ``ros2 topic echo`` relloc must compute exactly the hash ``rosidl`` generates.

The type description (``type_description_interfaces/msg/TypeDescription``) is

* ``type_description``: the type itself, ``{"type_name": "pkg/msg/Name", "fields": [...]}``,
* ``referenced_type_descriptions``: every type it uses, directly or not, sorted by name, each in
  the same form.

A field is ``{"name": ..., "type": {"type_id", "capacity", "string_capacity",
"nested_type_name"}}`` in that key order (the description's default values are left out of the
hash). ``type_id`` is the ``FieldType`` constant of the IDL type the ``.msg`` type maps to
(``bool`` -> boolean 15, ``byte`` -> octet 16, ``char`` -> uint8 3, ``float32`` -> float 10,
``float64`` -> double 11, ``string`` 17, ``string<=N`` 21, nested message 1, ...), plus 48 for
a fixed array, 96 for a bounded and 144 for an unbounded sequence. ``capacity`` is the array
size or the sequence bound (0 otherwise), ``string_capacity`` the bound of a bounded string (0 otherwise) and
``nested_type_name`` the nested message's full name (``""`` otherwise). A message without fields
has the one ``uint8 structure_needs_at_least_one_member`` rosidl adds. The JSON is written with
the separators ``", "`` and ``": "``, ASCII only, no sorting of keys.

The definitions come from a distribution's ``rosbags`` type store
(:func:`relloc.ros.stores.store`: the ROS 2 message definitions plus relloc's ``.msg`` files);
a type whose definition changed between distributions has one hash per layout.
``tests/test_rmw_zenoh.py`` checks the result against hashes published by ROS 2 itself.
"""

from __future__ import annotations

import hashlib
import json
from functools import cache
from typing import Any

from relloc.ros.stores import DEFAULT_DISTRO, MessageDecodeError, generation, store

__all__ = ["RIHS01_PREFIX", "type_description", "type_hash"]

RIHS01_PREFIX = "RIHS01_"

# FieldType constants of the IDL types that .msg primitive types map to (rosidl_adapter's map)
_BASE_TYPE_IDS = {
    "int8": 2,
    "uint8": 3,
    "char": 3,  # a .msg char is an IDL uint8
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "bool": 15,
    "byte": 16,  # octet
    "string": 17,
    "wstring": 18,
}
_NESTED = 1
_BOUNDED_STRING = {"string": 21, "wstring": 22}
_ARRAY, _BOUNDED_SEQUENCE, _UNBOUNDED_SEQUENCE = 48, 96, 144

# rosbags' node types of a field definition
_BASE, _NAME, _ARRAY_NODE, _SEQUENCE_NODE = 1, 2, 3, 4


def _value_type(nodetype: int, detail: Any) -> tuple[int, int, str]:
    """``(type_id, string_capacity, nested_type_name)`` of a non-array field type."""
    if nodetype == _NAME:
        return _NESTED, 0, str(detail)
    if nodetype != _BASE:
        raise MessageDecodeError(f"nested arrays cannot be described: {nodetype}, {detail}")
    name, bound = detail
    if bound and name in _BOUNDED_STRING:
        return _BOUNDED_STRING[name], int(bound), ""
    try:
        return _BASE_TYPE_IDS[name], 0, ""
    except KeyError:
        raise MessageDecodeError(f"no ROS 2 field type for {name!r}") from None


def _field_type(nodetype: int, detail: Any) -> dict[str, Any]:
    capacity = 0
    offset = 0
    if nodetype == _ARRAY_NODE:
        (inner, inner_detail), capacity = detail
        offset = _ARRAY
    elif nodetype == _SEQUENCE_NODE:
        (inner, inner_detail), capacity = detail
        offset = _BOUNDED_SEQUENCE if capacity else _UNBOUNDED_SEQUENCE
    else:
        inner, inner_detail = nodetype, detail
    type_id, string_capacity, nested = _value_type(int(inner), inner_detail)
    return {
        "type_id": type_id + offset,
        "capacity": int(capacity),
        "string_capacity": string_capacity,
        "nested_type_name": nested,
    }


def _individual(msgtype: str, distro: str) -> dict[str, Any]:
    fielddefs = store(distro).fielddefs
    if msgtype not in fielddefs:
        raise MessageDecodeError(f"unknown message type {msgtype!r}")
    _, fields = fielddefs[msgtype]
    described = [{"name": name, "type": _field_type(int(nt), d)} for name, (nt, d) in fields]
    if not described:  # rosidl gives an empty message one dummy member
        described = [
            {
                "name": "structure_needs_at_least_one_member",
                "type": _field_type(_BASE, ("uint8", 0)),
            }
        ]
    return {"type_name": msgtype, "fields": described}


def type_description(msgtype: str, distro: str = DEFAULT_DISTRO) -> dict[str, Any]:
    """The type description of ``msgtype`` (``"pkg/msg/Name"``) in ``distro``, in the form
    that is hashed."""
    return _description(msgtype, distro, generation())


@cache
def _description(msgtype: str, distro: str, _generation: int) -> dict[str, Any]:
    top = _individual(msgtype, distro)
    seen: dict[str, dict[str, Any]] = {}
    pending = [f["type"]["nested_type_name"] for f in top["fields"]]
    while pending:
        name = pending.pop()
        if name and name not in seen:
            seen[name] = _individual(name, distro)
            pending.extend(f["type"]["nested_type_name"] for f in seen[name]["fields"])
    return {
        "type_description": top,
        "referenced_type_descriptions": [seen[name] for name in sorted(seen)],
    }


def type_hash(msgtype: str, distro: str = DEFAULT_DISTRO) -> str:
    """The RIHS01 type hash of ``msgtype`` in ``distro``, e.g. ``"RIHS01_df668c74..."`` for
    ``std_msgs/msg/String``. Raises :class:`~relloc.ros.stores.MessageDecodeError` for a
    type the store does not know."""
    return _hash(msgtype, distro, generation())


@cache
def _hash(msgtype: str, distro: str, _generation: int) -> str:
    text = json.dumps(
        type_description(msgtype, distro),
        ensure_ascii=True,
        allow_nan=False,
        indent=None,
        separators=(", ", ": "),
        sort_keys=False,
    )
    return RIHS01_PREFIX + hashlib.sha256(text.encode("utf-8")).hexdigest()
