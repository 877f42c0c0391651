"""One ``rosbags`` type store per ROS 2 distribution, with relloc's and registered types.

``rosbags`` ships the message definitions of each distribution; relloc adds its ``.msg`` files
(``relloc/ros/msg``: the TIERS detection types) and those a sensor or a team config registers
(:func:`register_types`: a UWB driver's own message). A type a newer distribution dropped but a
registered type uses (``geometry_msgs/msg/Pose2D``) is taken from the oldest store that has it.
:func:`generation` changes whenever a registration changes the stores, so that what is
computed from them (layouts, hashes) can be cached per generation.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import cache
from pathlib import Path
from typing import Any, Final, get_args

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from relloc.config import ConfigError, RosDistro

__all__ = [
    "DEFAULT_DISTRO",
    "DISTROS",
    "MSG_DIR",
    "MessageDecodeError",
    "check_distro",
    "custom_types",
    "generation",
    "register_types",
    "store",
]

DISTROS: Final[tuple[str, ...]] = get_args(RosDistro)
"""The distributions relloc knows, oldest first (:data:`relloc.config.RosDistro`)."""
DEFAULT_DISTRO: Final = "jazzy"
"""The current LTS."""

_STORES: Final = {
    "humble": Stores.ROS2_HUMBLE,
    "iron": Stores.ROS2_IRON,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
    "lyrical": Stores.ROS2_LYRICAL,
    "rolling": Stores.LATEST,
}

MSG_DIR = Path(__file__).resolve().parent / "msg"
"""Custom ``.msg`` definitions shipped with the package, laid out ``<pkg>/msg/<Type>.msg``."""


class MessageDecodeError(ValueError):
    """A CDR payload could not be decoded as the expected message type (or the type is unknown)."""


_EXTRA: dict[str, Any] = {}
"""Definitions registered on top of every distribution's store (sensors' and users' types)."""
_BUILT: dict[str, Typestore] = {}
_GENERATION = [0]


def check_distro(name: str) -> str:
    """``name`` if it is a known distribution, else a :class:`ConfigError`."""
    if name not in DISTROS:
        raise ConfigError(f"unknown ROS 2 distribution {name!r}; known: {', '.join(DISTROS)}")
    return name


def custom_types(folder: Path = MSG_DIR) -> dict[str, Any]:
    """Parse every ``.msg`` file of ``folder`` (laid out ``<pkg>/msg/<Type>.msg``; the shipped
    ones by default) into a ``rosbags`` types dict (name -> definition)."""
    types: dict[str, Any] = {}
    for path in sorted(folder.glob("*/msg/*.msg")):
        name = f"{path.parent.parent.name}/msg/{path.stem}"
        types.update(get_types_from_msg(path.read_text(), name))
    return types


def generation() -> int:
    """A number that changes whenever registered types change the stores."""
    return _GENERATION[0]


def store(distro: str = DEFAULT_DISTRO) -> Typestore:
    """The type store of ``distro`` with relloc's and the registered extra types (built once)."""
    built = _BUILT.get(distro)
    if built is None:
        built = get_typestore(_STORES[check_distro(distro)])
        own = {**custom_types(), **_EXTRA}
        built.register(own)
        built.register(_missing_dependencies(built, own))
        _BUILT[distro] = built
    return built


def _missing_dependencies(built: Typestore, types: Mapping[str, Any]) -> dict[str, Any]:
    """The types ``types`` use, directly or not, that ``built`` lacks (a type a newer
    distribution dropped, e.g. ``geometry_msgs/msg/Pose2D``), from the oldest store that has
    them: a driver's message keeps the layout it was written with."""
    fallback = _oldest()
    found: dict[str, Any] = {}
    pending = list(types.values())
    while pending:
        _, fields = pending.pop()
        for _, (nodetype, detail) in fields:
            name = _nested_name(int(nodetype), detail)
            missing = (
                name and name not in built.fielddefs and name not in types and name not in found
            )
            if missing and name in fallback.fielddefs:
                found[name] = fallback.fielddefs[name]
                pending.append(found[name])
    return found


@cache
def _oldest() -> Typestore:
    """The oldest distribution's store as ``rosbags`` ships it (built once: where a type a newer
    one dropped is found)."""
    return get_typestore(_STORES[DISTROS[0]])


def _nested_name(nodetype: int, detail: Any) -> str:
    """The message type a field of rosbags' node type names (``""`` for a base type)."""
    if nodetype in (3, 4):  # array, sequence: ((inner node type, inner detail), size)
        (inner, inner_detail), _ = detail
        return _nested_name(int(inner), inner_detail)
    return str(detail) if nodetype == 2 else ""


def register_types(types: Mapping[str, Any]) -> None:
    """Add message definitions to every distribution's store (built and future ones). A type
    registered again with another definition (a driver's two layouts, one config after the
    other) replaces the first: the stores are built anew."""
    replaced = any(name in _EXTRA and _EXTRA[name] != value for name, value in types.items())
    _EXTRA.update(types)
    if replaced:
        _BUILT.clear()
    for built in _BUILT.values():
        built.register(dict(types))
        built.register(_missing_dependencies(built, types))
    _GENERATION[0] += 1
