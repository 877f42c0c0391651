"""ROS 2 distributions: the layouts of a type, and the hash in rmw_zenoh keys and tokens.

A message type can differ between distributions: ``sensor_msgs/msg/Range`` ends with
``float32 variance`` since Iron. Each layout of a type has its own RIHS01 hash
(:func:`relloc.ros.type_hash.type_hash` on that distribution's store,
:mod:`relloc.ros.stores`), and rmw_zenoh drops a sample whose hash is not the subscriber's.
So relloc:

* decodes a payload of an unknown layout by trying each known one (:func:`layouts`, the
  configured distribution's first): the CDR size check tells them apart;
* picks the layout from a sample's hash chunk when the hash is known (:func:`layout_of_hash`),
  or from a bag's stored definition (:func:`layout_of_definition`);
* writes, in keys and tokens, the hash a node of the configured distribution writes
  (:func:`key_hash`): rmw_zenoh for Humble writes ``TypeHashNotSupported``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, cached_property
from typing import Final

from rosbags.typesys import get_types_from_msg
from rosbags.typesys.store import Typestore

from relloc.ros.stores import DEFAULT_DISTRO, DISTROS, check_distro, generation, store
from relloc.ros.type_hash import type_hash

__all__ = [
    "DEFAULT_DISTRO",
    "DISTROS",
    "HASH_NOT_SUPPORTED",
    "Layout",
    "key_hash",
    "layout_of_definition",
    "layout_of_hash",
    "layouts",
]

HASH_NOT_SUPPORTED: Final = "TypeHashNotSupported"
"""The hash chunk of rmw_zenoh for Humble, which has no type hashes."""


@dataclass(frozen=True)
class Layout:
    """One definition of a message type, shared by one or more distributions."""

    msgtype: str
    distros: tuple[str, ...]
    """The distributions with this definition, oldest first."""
    hash: str
    """Its RIHS01 hash."""

    @property
    def name(self) -> str:
        """``humble`` for one distribution, ``iron..rolling`` for a run of them."""
        first, last = self.distros[0], self.distros[-1]
        return first if first == last else f"{first}..{last}"

    @property
    def store(self) -> Typestore:
        return store(self.distros[0])

    @cached_property
    def fields(self) -> tuple[str, ...]:
        """Its field names, in order."""
        return tuple(name for name, _ in self.store.fielddefs[self.msgtype][1])

    def __str__(self) -> str:
        return f"{self.msgtype}@{self.name}"


def layouts(msgtype: str, first: str = DEFAULT_DISTRO) -> tuple[Layout, ...]:
    """The distinct layouts of ``msgtype`` among the distributions whose store knows it, the
    layout of ``first`` first. Empty if no store knows the type."""
    return _layouts(msgtype, first, generation())


@cache
def _layouts(msgtype: str, first: str, _generation: int) -> tuple[Layout, ...]:
    found: dict[str, list[str]] = {}
    for distro in DISTROS:
        st = store(distro)
        if msgtype in st.fielddefs:
            found.setdefault(type_hash(msgtype, distro), []).append(distro)
    out = [Layout(msgtype, tuple(ds), h) for h, ds in found.items()]
    out.sort(key=lambda lay: first not in lay.distros)
    return tuple(out)


@cache
def _by_hash(msgtype: str, _generation: int) -> dict[str, Layout]:
    return {lay.hash: lay for lay in layouts(msgtype)}


def layout_of_hash(msgtype: str, hash_: str | None) -> Layout | None:
    """The layout of ``msgtype`` whose RIHS01 hash is ``hash_``, or ``None`` (unknown hash,
    ``TypeHashNotSupported``, no hash)."""
    return _by_hash(msgtype, generation()).get(hash_ or "")


def layout_of_definition(msgtype: str, text: str) -> Layout | None:
    """The known layout of ``msgtype`` whose fields are those of the ``.msg`` text ``text`` (a
    bag's stored definition, dependencies appended as rosbag2 writes them), or ``None``."""
    try:
        parsed = get_types_from_msg(text, msgtype)
    except Exception:  # a definition rosbags cannot parse tells nothing
        return None
    if msgtype not in parsed:
        return None
    names = tuple(name for name, _ in parsed[msgtype][1])
    return next((lay for lay in layouts(msgtype) if lay.fields == names), None)


def key_hash(msgtype: str, distro: str = DEFAULT_DISTRO) -> str:
    """The hash chunk a ``distro`` node puts in keys and tokens for ``msgtype``."""
    if check_distro(distro) == "humble":
        return HASH_NOT_SUPPORTED
    return type_hash(msgtype, distro)
