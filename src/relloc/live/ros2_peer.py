"""An independent ROS 2 peer for relloc's live commands, made with ``zenoh-ros2-sdk``.

ROBOTIS' pure-Python rmw_zenoh client stands in for real ROS 2 robots and consumers: its own
type hashes, keys, attachments and liveliness tokens, none of relloc's wire code. The SDK
fetches message definitions by cloning git repositories at run time; here it never does:
:func:`write_messages` writes one distribution's ``.msg`` files (from the ``rosbags`` type
store) into a folder and :class:`Ros2Peer` points the SDK at that folder alone, with the clone
functions replaced by ones that only record the attempt (:attr:`Ros2Peer.clone_attempts`).

The team and the measurement, a whole run against ``relloc serve``, are
:mod:`relloc.live.peer_run`'s.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rosbags.typesys import Stores, get_typestore

ODOMETRY = "nav_msgs/msg/Odometry"
RANGE = "sensor_msgs/msg/Range"
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TWIST = "geometry_msgs/msg/Twist"
STRING = "std_msgs/msg/String"
PEER_TYPES = (ODOMETRY, RANGE, POSE, TWIST, STRING)
"""The types the peer speaks; their nested types are written too."""

STORES = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}
HASH_NOT_SUPPORTED = "TypeHashNotSupported"
"""What rmw_zenoh for Humble writes in the hash chunk of keys and tokens."""
RANGE_HASHES = {
    "humble": "RIHS01_9430b1915b94d4268ff903679e8ecd09b6a67d331bd028738ec1eeb592891ebd",
    "jazzy": "RIHS01_b42b62562e93cbfe9d42b82fe5994dfa3d63d7d5c90a317981703f7388adff3a",
}
"""RIHS01 of ``sensor_msgs/msg/Range``: Humble's layout, and Iron's on (``float32 variance``)."""
TIME_BASE = 1_700_000_000.0
"""Added to the simulator's stamps on the wire (as relloc's own publishers do)."""


# ---------------------------------------------------------------------------- definitions
def _type_text(nodetype: Any, detail: Any) -> str:
    """A ``rosbags`` field type as ``.msg`` text (``float64[36]``, ``string<=8``, ``pkg/msg/T[]``)."""
    kind = int(nodetype)
    if kind == 1:  # base type, with a string bound
        name, bound = detail
        return f"{name}<={bound}" if bound else str(name)
    if kind == 2:  # nested message
        return str(detail)
    (inner_type, inner_detail), size = detail
    inner = _type_text(inner_type, inner_detail)
    if kind == 3:  # fixed array
        return f"{inner}[{size}]"
    return f"{inner}[<={size}]" if size else f"{inner}[]"  # sequence


def msg_text(distro: str, msgtype: str) -> str:
    """The ``.msg`` definition of ``msgtype`` in ``distro``'s ``rosbags`` store (constants
    first, nested types by full name)."""
    consts, fields = get_typestore(STORES[distro]).fielddefs[msgtype]
    lines = [f"{ctype} {name}={value}" for name, ctype, value in consts]
    lines += [f"{_type_text(*ftype)} {name}" for name, ftype in fields]
    return "\n".join(lines) + "\n"


def closure(distro: str, msgtypes: Iterable[str] = PEER_TYPES) -> list[str]:
    """``msgtypes`` and every type they use, directly or not, sorted."""
    fielddefs = get_typestore(STORES[distro]).fielddefs
    seen: set[str] = set()
    pending = list(msgtypes)
    while pending:
        name = pending.pop()
        if name in seen:
            continue
        seen.add(name)
        fields: list[tuple[str, Any]] = fielddefs[name][1]  # rosbags' nested field unions
        for _, (nodetype, detail) in fields:
            while int(nodetype) in (3, 4):  # arrays and sequences of ...
                (nodetype, detail), _ = detail
            if int(nodetype) == 2:
                pending.append(str(detail))
    return sorted(seen)


def write_messages(distro: str, folder: Path) -> Path:
    """Write the peer's types of ``distro`` as ``<folder>/<pkg>/msg/<Name>.msg`` (the SDK's
    messages layout); returns ``folder``."""
    for name in closure(distro):
        pkg, _, leaf = name.split("/")
        path = folder / pkg / "msg" / f"{leaf}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(msg_text(distro, name))
    return folder


def rihs01(msgtype: str, messages: Path) -> str:
    """The RIHS01 hash the SDK computes for ``msgtype`` from the definitions in ``messages``
    (no session needed)."""
    from zenoh_ros2_sdk.message_registry import MessageRegistry
    from zenoh_ros2_sdk.utils import get_type_hash, load_dependencies_recursive

    registry = MessageRegistry(str(messages))
    pkg, _, leaf = msgtype.split("/")
    text = (messages / pkg / "msg" / f"{leaf}.msg").read_text()
    deps = load_dependencies_recursive(msgtype, text, registry)
    return str(get_type_hash(msgtype, msg_definition=text, dependencies=deps))


# ---------------------------------------------------------------------------- the SDK, offline
def reset_sdk() -> None:
    """Close the SDK's process-wide session and forget its message registry."""
    from zenoh_ros2_sdk import message_registry
    from zenoh_ros2_sdk.session import ZenohSession

    if ZenohSession._instance is not None:
        ZenohSession._instance.close()
    ZenohSession._instance = None
    message_registry._registry = None


@contextmanager
def offline_sdk(messages: Path) -> Iterator[list[str]]:
    """The SDK reading definitions from ``messages`` only: a fresh registry on that folder, an
    empty cache folder, and its clone functions replaced by a recorder that raises. Yields the
    list of repositories it tried to clone (the SDK logs and swallows the failure)."""
    from zenoh_ros2_sdk import _cache, message_registry

    attempts: list[str] = []

    def refuse(repo: Any, *args: Any, **kwargs: Any) -> Any:
        attempts.append(str(repo))
        raise RuntimeError(f"the test peer never clones ({repo})")

    class NoRepo:
        clone_from = staticmethod(refuse)

        def __init__(self, path: Any, *args: Any, **kwargs: Any) -> None:
            refuse(path)

    patches = [
        (_cache, "clone_to_cache", refuse),
        (_cache, "Repo", NoRepo),
        (message_registry, "clone_to_cache", refuse),
        (message_registry, "_registry", message_registry.MessageRegistry(str(messages))),
    ]
    saved = [(obj, name, getattr(obj, name)) for obj, name, _ in patches]
    env = {"ZENOH_ROS2_SDK_CACHE": str(messages / ".no-cache")}
    saved_env = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    for obj, name, value in patches:
        setattr(obj, name, value)
    try:
        yield attempts
    finally:
        for obj, name, value in reversed(saved):
            setattr(obj, name, value)
        _restore_env(saved_env)


def _restore_env(saved: dict[str, str | None]) -> None:
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@dataclass
class Inbox:
    """What one SDK subscriber received: the messages, counted, in arrival order."""

    topic: str
    messages: list[Any] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, msg: Any) -> None:
        with self.lock:
            self.messages.append(msg)

    @property
    def count(self) -> int:
        with self.lock:
            return len(self.messages)

    def snapshot(self) -> list[Any]:
        with self.lock:
            return list(self.messages)


class Ros2Peer:
    """One SDK session on ``127.0.0.1:port`` speaking ``distro``'s definitions from ``messages``.

    Humble keys and tokens carry ``TypeHashNotSupported``, as rmw_zenoh for Humble writes;
    later distributions the RIHS01 hash the SDK computes from the definitions. Everything the
    SDK would fetch from git is recorded in :attr:`clone_attempts` instead (and fails).
    Use as a context manager; :meth:`close` closes the session and restores the SDK.
    """

    def __init__(self, distro: str, messages: Path, port: int, *, domain_id: int = 0) -> None:
        from zenoh_ros2_sdk.session import ZenohSession

        if distro not in STORES:
            raise ValueError(f"unknown distribution {distro!r}; known: {sorted(STORES)}")
        self.distro = distro
        self.messages = messages
        self.port = port
        self.domain_id = domain_id
        self.publishers: list[Any] = []
        self.subscribers: list[Any] = []
        reset_sdk()
        self._offline = offline_sdk(messages)
        self.clone_attempts: list[str] = self._offline.__enter__()
        """Repositories the SDK tried to clone (and was refused)."""
        env = {
            "ZENOH_CONFIG_OVERRIDE": 'scouting/multicast/enabled=false;listen/endpoints=["tcp/127.0.0.1:0"]',
            "ZENOH_SESSION_CONFIG_URI": "",
        }
        self._env = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
        self.session = ZenohSession.get_instance("127.0.0.1", port)

    def __enter__(self) -> Ros2Peer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def key_hash(self, msgtype: str) -> str | None:
        """The hash to put in keys: ``None`` lets the SDK compute RIHS01 (Iron on)."""
        return HASH_NOT_SUPPORTED if self.distro == "humble" else None

    def publisher(self, topic: str, msgtype: str, *, node: str = "sdk_peer") -> Any:
        """An SDK publisher of ``msgtype`` on ``topic``."""
        from zenoh_ros2_sdk import ROS2Publisher

        pub = ROS2Publisher(
            topic, msgtype, node_name=node, domain_id=self.domain_id, router_port=self.port,
            type_hash=self.key_hash(msgtype),
        )  # fmt: skip
        self.publishers.append(pub)
        return pub

    def subscribe(
        self, topic: str, msgtype: str, *, type_hash: str | None = None, node: str = "sdk_listener"
    ) -> Inbox:
        """An SDK subscriber of ``msgtype`` on ``topic`` collecting into an :class:`Inbox`;
        ``type_hash`` overrides the distribution's (to hear a node of another one)."""
        from zenoh_ros2_sdk import ROS2Subscriber

        inbox = Inbox(topic)
        sub = ROS2Subscriber(
            topic, msgtype, inbox, node_name=node, domain_id=self.domain_id,
            router_port=self.port, type_hash=type_hash or self.key_hash(msgtype),
        )  # fmt: skip
        self.subscribers.append(sub)
        return inbox

    def rihs01(self, msgtype: str) -> str:
        """The RIHS01 hash the SDK computes for ``msgtype`` from the peer's definitions."""
        return rihs01(msgtype, self.messages)

    def types(self) -> Any:
        """The SDK session's message classes (``types[name](**fields)``)."""
        return self.session.store.types

    def topics(self, timeout: float = 0.5) -> dict[str, list[str]]:
        """``ros2 topic list -t`` as the SDK's discovery sees it: name -> types."""
        from zenoh_ros2_sdk import get_topic_names_and_types

        found = get_topic_names_and_types(
            domain_id=self.domain_id, router_port=self.port, timeout=timeout
        )
        return dict(found)

    def topic_info(self, topic: str, timeout: float = 0.5) -> Any:
        """``ros2 topic info -v``: publishers and subscribers with type hashes (or ``None``)."""
        from zenoh_ros2_sdk import get_topic_info

        return get_topic_info(
            topic, domain_id=self.domain_id, router_port=self.port, timeout=timeout, verbose=True
        )

    def close(self) -> None:
        for entity in [*self.subscribers, *self.publishers]:
            entity.close()
        self.subscribers, self.publishers = [], []
        reset_sdk()
        _restore_env(self._env)
        self._offline.__exit__(None, None, None)
