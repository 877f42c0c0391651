"""CDR in every layout of a type: decode, encode, and move a message from one layout to another.

A message type may be laid out differently in two ROS 2 distributions (``sensor_msgs/msg/Range``
has a ``variance`` since Iron: :mod:`relloc.ros.distros`). :func:`decode` reads a payload in the
layout it is told or in the first known one it fits (the CDR size check tells them apart), and
says why not with a :class:`~relloc.ros.stores.MessageDecodeError`; :func:`encode` writes a
message in the layout of the store that made it or of a given distribution, converting it
(:func:`in_layout`: fields copied by name, new ones zero). :func:`in_distro` does both for a raw
payload (a replayed bag), :func:`zero_message` builds an all-zero message of a type.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore

from relloc.ros.distros import Layout, layouts
from relloc.ros.stores import DEFAULT_DISTRO, DISTROS, MessageDecodeError, store

__all__ = ["decode", "encode", "in_distro", "in_layout", "typestore", "zero_message"]


def typestore(distro: str = DEFAULT_DISTRO) -> Typestore:
    """The type store of ``distro`` (:func:`relloc.ros.distros.store`), built once per process
    (``rosbags`` generates Python classes for every registered type)."""
    return store(distro)


def decode(raw: bytes | memoryview, msgtype: str, layout: Layout | None = None) -> Any:
    """Deserialise a CDR payload (with its 4-byte encapsulation header) into a message object,
    in ``layout``, else in the first known layout of the type it fits (the CDR size tells them
    apart).

    Raises :class:`MessageDecodeError` for an unknown type or any malformed payload (truncated,
    garbage, trailing bytes, invalid strings).
    """
    tried = (layout,) if layout is not None else layouts(msgtype)
    if not tried:
        raise MessageDecodeError(f"unknown message type {msgtype!r}")
    error: Exception | None = None
    for lay in tried:
        try:
            return lay.store.deserialize_cdr(raw, msgtype)
        except Exception as exc:  # the deserialiser raises many types on garbage; normalise them
            error = exc
    assert error is not None
    which = (
        f" in layout {tried[0].name}" if len(tried) == 1 else f" in any of its {len(tried)} layouts"
    )
    raise MessageDecodeError(
        f"malformed {msgtype} payload ({len(raw)} bytes){which}: {type(error).__name__}: {error}"
    ) from error


def encode(msg: Any, msgtype: str | None = None, distro: str | None = None) -> bytes:
    """Serialise a message object to CDR (little endian, with encapsulation header).

    ``msgtype`` defaults to the message's own ``__msgtype__``. With ``distro`` the message is
    written in that distribution's layout (fields it lacks are dropped, fields it adds are
    zero); otherwise in the layout of the store that made it.
    """
    typename = msgtype or msg.__msgtype__
    if distro is not None:
        target = store(distro)
        return bytes(target.serialize_cdr(in_layout(msg, target), typename, little_endian=True))
    return bytes(_store_of(msg).serialize_cdr(msg, typename, little_endian=True))


def in_distro(raw: bytes, msgtype: str, distro: str) -> bytes:
    """A CDR payload of ``msgtype`` in ``distro``'s layout: ``raw`` itself when the type has
    one layout (or ``raw`` fits ``distro``'s), else decoded and written again. A payload no
    layout fits is returned as it is (the receiver counts it)."""
    known = layouts(msgtype, distro)
    if len(known) < 2:
        return raw
    for lay in known:  # the distribution's own layout first
        try:
            msg = decode(raw, msgtype, lay)
        except MessageDecodeError:
            continue
        return raw if lay is known[0] else encode(msg, msgtype, distro)
    return raw


def _store_of(msg: Any) -> Typestore:
    """The store whose class ``msg`` is an instance of (the default one for a foreign object)."""
    name = getattr(msg, "__msgtype__", "")
    for distro in (DEFAULT_DISTRO, *DISTROS):
        st = store(distro)
        if st.types.get(name) is type(msg):
            return st
    return store()


def in_layout(msg: Any, target: Typestore) -> Any:
    """``msg`` as an object of ``target``'s class of its type: fields copied by name (nested
    messages converted), fields ``target`` adds set to zero, fields it lacks dropped."""
    name = msg.__msgtype__
    cls = target.types[name]
    if type(msg) is cls:
        return msg
    values = {}
    for field_name, (nodetype, detail) in target.fielddefs[name][1]:
        if hasattr(msg, field_name):
            value = getattr(msg, field_name)
            if hasattr(value, "__msgtype__"):
                value = in_layout(value, target)
            elif isinstance(value, list):
                value = [in_layout(v, target) if hasattr(v, "__msgtype__") else v for v in value]
            values[field_name] = value
        else:
            values[field_name] = _zero(target, int(nodetype), detail)
    return cls(**values)


def zero_message(msgtype: str, distro: str = DEFAULT_DISTRO) -> Any:
    """A message of ``msgtype`` (in ``distro``'s layout) with every field zero, empty or
    false: a base to set the fields a publisher knows (a UWB driver's frame in a test)."""
    target = store(distro)
    return _zero(target, 2, msgtype)


def _zero(target: Typestore, nodetype: int, detail: Any) -> Any:
    """The zero value of a field (1 base, 2 message, 3 array, 4 sequence: rosbags' node types)."""
    if nodetype == 2:
        return target.types[str(detail)](**{
            n: _zero(target, int(nt), d) for n, (nt, d) in target.fielddefs[str(detail)][1]
        })  # fmt: skip
    if nodetype == 3:  # a fixed-size array: that many zeros
        (inner, inner_detail), size = detail
        if int(inner) == 1 and inner_detail[0] not in ("string", "wstring", "bool"):
            return np.zeros(size, dtype=_NUMPY.get(inner_detail[0], np.float64))
        return [_zero(target, int(inner), inner_detail) for _ in range(size)]
    if nodetype == 4:
        return []
    base = detail[0]
    if base in ("string", "wstring"):
        return ""
    return False if base == "bool" else (0.0 if base.startswith("float") else 0)


_NUMPY = {
    "float32": np.float32, "float64": np.float64, "int8": np.int8, "uint8": np.uint8, "char": np.uint8,
    "byte": np.uint8, "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
    "int64": np.int64, "uint64": np.uint64,
}  # fmt: skip
