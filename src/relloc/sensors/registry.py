"""The registered sensors: one descriptor per kind, looked up by kind or by event type.

:func:`register` makes a :class:`~relloc.sensors.base.Sensor` known everywhere at once: its
kind to the ingestion layer (routes, conversion, counters), its message definitions to relloc's
type store (:func:`relloc.ros.messages.register_types`) and its measurement model to
:mod:`relloc.filter.registry`. The built-in sensors are registered when :mod:`relloc.sensors`
is imported; a plug-in registers its own and may :func:`unregister` it again (its message
definitions stay in the type store: they name types of their own and harm nothing).
Registration order is the order routes are listed in.
"""

from __future__ import annotations

from relloc.config import ConfigError, TeamConfig
from relloc.filter import registry as models
from relloc.ros.messages import register_types
from relloc.sensors.base import Sensor

__all__ = ["check_config", "kind_of", "register", "registered", "sensor", "sensor_of", "unregister"]

_SENSORS: dict[str, Sensor] = {}
_OF_EVENT: dict[type, Sensor] = {}


def register(descriptor: Sensor) -> None:
    """Make ``descriptor`` the sensor of its kind and of its event type (module docstring).
    Raises :class:`ValueError` if another sensor has that kind or event type."""
    kind = descriptor.kind
    taken = _SENSORS.get(kind) or _OF_EVENT.get(descriptor.event)
    if taken is not None and taken is not descriptor:
        raise ValueError(
            f"sensor {kind!r}: kind or event type {descriptor.event.__name__} already registered by {taken.kind!r}"
        )
    if descriptor.msg_types:
        register_types(descriptor.msg_types)
    _SENSORS[kind] = descriptor
    _OF_EVENT[descriptor.event] = descriptor
    if descriptor.model is not None:
        models.register(descriptor.model)


def unregister(descriptor: Sensor) -> None:
    """Forget ``descriptor`` (and its measurement model): a plug-in switched off again."""
    if _SENSORS.get(descriptor.kind) is descriptor:
        del _SENSORS[descriptor.kind]
        del _OF_EVENT[descriptor.event]
        if descriptor.model is not None:
            models.unregister(descriptor.model)


def registered() -> tuple[Sensor, ...]:
    """Every registered sensor, in registration order."""
    return tuple(_SENSORS.values())


def sensor(kind: str) -> Sensor:
    """The sensor of ``kind``; :class:`KeyError` naming the known kinds if there is none."""
    try:
        return _SENSORS[kind]
    except KeyError:
        raise KeyError(f"no sensor of kind {kind!r}; registered: {sorted(_SENSORS)}") from None


def sensor_of(event: object) -> Sensor | None:
    """The sensor whose events are of ``event``'s type, or ``None``."""
    return _OF_EVENT.get(type(event))


def kind_of(event: object) -> str:
    """The kind an event is counted under: its sensor's, else its class name."""
    found = _OF_EVENT.get(type(event))
    return found.kind if found is not None else type(event).__name__


def check_config(config: TeamConfig) -> None:
    """Raise :class:`~relloc.config.ConfigError` if the config has a ``sensors`` table of no
    registered sensor (a misspelt or not loaded plug-in); each sensor checks its own table."""
    unknown = sorted(set(config.sensors) - set(_SENSORS))
    if unknown:
        raise ConfigError(
            f"sensors.{unknown[0]}: no sensor plug-in of that name is registered "
            f"(registered: {sorted(_SENSORS)}); register its descriptor before loading data"
        )
    for descriptor in _SENSORS.values():
        descriptor.settings(config)
