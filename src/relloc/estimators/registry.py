"""The registry of estimator kinds (``[filter] kind``): what each can do, and how ``auto`` picks.

A kind is one package of :mod:`relloc.estimators` (or one module of a user's) that registers a
:class:`Kind`: its name, its localizer (as ``"module:Class"``, imported only when the kind
runs, so a process running the particle filter does not load GTSAM), its
:class:`Capabilities` and when it suits a team (``suits``). Config checks
(:func:`check`), the automatic choice (:func:`choose`), the command line's ``--filter-kind``
and the docs' capability table read this registry; nothing else names a kind.

``auto`` takes the registered kinds by ``priority`` (lowest first), keeps those that can do
what the config's modes ask (headings, odometry scales, online biases), and picks the first
whose ``suits`` gives a reason for the team; a kind whose ``suits`` is ``None`` is only run when
named.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any, Protocol

from relloc.config import ConfigError, TeamConfig

if TYPE_CHECKING:
    from relloc.estimate import Estimate
    from relloc.events import Event


@dataclass(frozen=True)
class Capabilities:
    """What a kind estimates and fuses beyond positions from odometry and ranges."""

    headings: bool = False
    """Estimates each robot's heading relative to the reference (``heading_mode = "estimate"``)."""
    scales: bool = False
    """Estimates odometry scales online (``odom_scale_mode = "online"``)."""
    online_biases: bool = False
    """Estimates UWB pair biases online (``bias_mode = "online"``)."""
    sightings: bool = True
    """Fuses camera sightings of teammates (range and bearing)."""
    detections: bool = True
    """Fuses cooperative detections (relative positions)."""
    smoothed: bool = False
    """Gives the whole run smoothed afterwards (``smoothed_estimates()``, the ``_smoothed`` row)."""
    dimensions: tuple[int, ...] = (2,)
    """The spatial dimensions it estimates in."""


MODE_NEEDS: dict[str, tuple[str, str, str]] = {
    "heading_mode": ("estimate", "headings", "estimate the headings"),
    "odom_scale_mode": ("online", "scales", "estimate the odometry scales"),
    "bias_mode": ("online", "online_biases", "estimate the range biases online"),
}
"""``[filter.self_calibration]`` key -> (the value that asks for it, the capability, what)."""


class Estimator(Protocol):
    """What the engine, the live server and the evaluation ask of a kind's localizer."""

    method: str
    stats: Any

    def process(self, event: Event) -> list[Estimate]:
        """Take one event (time-ordered); the estimates it completes."""
        ...

    def flush(self) -> list[Estimate]:
        """The estimates still pending at the end of a source."""
        ...

    def fault_counters(self) -> dict[str, Any]:
        """Rejections and fault states, for the run's JSON and the live status."""
        ...


@dataclass(frozen=True)
class Kind:
    """One estimator kind (module docstring)."""

    name: str
    localizer: str
    """``"package.module:Class"``; the class takes ``(config, *, seed, method)``."""
    capabilities: Capabilities
    summary: str
    """One line for the docs' capability table."""
    priority: int = 100
    suits: Callable[[TeamConfig], str | None] = lambda config: None
    """Why ``auto`` should pick this kind for a team (``None``: it should not)."""

    def load(self) -> type[Any]:
        """The localizer class (imports its module)."""
        module, _, name = self.localizer.partition(":")
        cls: type[Any] = getattr(importlib.import_module(module), name)
        return cls

    def cannot(self, config: TeamConfig) -> str | None:
        """What of the config's modes this kind cannot do (``None``: it can do all)."""
        if config.dimension not in self.capabilities.dimensions:
            return f"estimate in {config.dimension}D (dimension = {config.dimension})"
        modes = config.filter.self_calibration
        for key, (value, capability, what) in MODE_NEEDS.items():
            if getattr(modes, key) == value and not getattr(self.capabilities, capability):
                return f"{what} (filter.self_calibration.{key} = {value!r})"
        return None


KINDS: dict[str, Kind] = {}
"""Registered kinds by name, in registration order."""


def register(kind: Kind) -> Kind:
    """Add ``kind`` (replacing one of the same name); returns it."""
    if kind.name == "auto":
        raise ValueError("'auto' is the automatic choice, not a kind")
    KINDS[kind.name] = kind
    return kind


def unregister(name: str) -> None:
    """Remove the kind ``name`` (a plug-in switched off again)."""
    KINDS.pop(name, None)


def names() -> tuple[str, ...]:
    """The registered kinds' names, and ``auto``: what ``[filter] kind`` may be."""
    return ("auto", *KINDS)


def get(name: str) -> Kind:
    """The kind ``name``; a :class:`ConfigError` naming the registered ones if unknown."""
    kind = KINDS.get(name)
    if kind is None:
        raise ConfigError(f"filter.kind = {name!r}: expected one of {', '.join(names())}")
    return kind


def check(config: TeamConfig) -> None:
    """A :class:`ConfigError` if the config names an unknown kind or one that cannot do what its
    modes ask."""
    if config.filter.kind == "auto":
        return
    kind = get(config.filter.kind)
    what = kind.cannot(config)
    if what is not None:
        able = [k.name for k in KINDS.values() if k.cannot(config) is None]
        raise ConfigError(
            f"filter.kind = {kind.name!r} cannot {what}: use kind = "
            + " or ".join(repr(n) for n in [*able, "auto"])
        )


def choose(config: TeamConfig) -> tuple[Kind, str]:
    """The kind that runs as ``pf`` and why (module docstring); checks the config first."""
    check(config)
    if config.filter.kind != "auto":
        return KINDS[config.filter.kind], "the config's"
    for kind in sorted(KINDS.values(), key=lambda k: k.priority):
        if kind.cannot(config) is not None:
            continue
        reason = kind.suits(config)
        if reason is not None:
            return kind, reason
    raise ConfigError("no registered filter kind can run this team's modes")


def capability_table() -> str:
    """The registry as a Markdown table (the docs' capability table)."""
    columns = [f.name for f in fields(Capabilities)]
    head = "| kind | " + " | ".join(c.replace("_", " ") for c in columns) + " | what it is |"
    rows = [head, "|" + "---|" * (len(columns) + 2)]
    for kind in KINDS.values():
        caps = kind.capabilities
        cells = []
        for c in columns:
            value = getattr(caps, c)
            cells.append(
                ", ".join(f"{d}D" for d in value)
                if isinstance(value, tuple)
                else ("yes" if value else "no")
            )
        rows.append(f"| `{kind.name}` | " + " | ".join(cells) + f" | {kind.summary} |")
    return "\n".join(rows) + "\n"
