"""The checking machinery of the config dataclasses: every field checked against its annotation
whenever one is made (from a file, by :func:`dataclasses.replace` or in code), tables built
with unknown keys rejected, and the range checks of numeric fields. A typo or an impossible
value is a :class:`ConfigError` naming the key, never a silent default."""

from __future__ import annotations

import functools
import math
import numbers
from dataclasses import fields, replace
from types import UnionType
from typing import Any, Literal, get_args, get_origin, get_type_hints


class ConfigError(ValueError):
    """The team configuration is invalid; the message says which key and why."""


class FieldError(ConfigError):
    """A field's value does not fit its annotation (:func:`build` adds where it was read)."""


class Checked:
    """Base of the config dataclasses: every field is checked against its annotation whenever
    one is made (:func:`check_value`)."""

    def __post_init__(self) -> None:
        cls: type = type(self)
        hints = type_hints(cls)
        for f in fields(self):  # type: ignore[arg-type]
            check_value(hints[f.name], getattr(self, f.name), f.name)


@functools.cache
def type_hints(cls: type) -> dict[str, Any]:
    return get_type_hints(cls)


def check_value(hint: Any, value: Any, where: str) -> None:
    """``value`` fits ``hint``: numbers finite (not booleans), integers integral, booleans
    real booleans, strings strings, ``Literal`` choices spelled right; other hints unchecked."""
    if hint is bool and not isinstance(value, bool):
        raise FieldError(f"{where}: expected true or false, got {value!r}")
    numeric = hint in (float, int) or (
        get_origin(hint) is UnionType and float in get_args(hint) and value is not None
    )
    if numeric and (
        isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value)
    ):
        raise FieldError(f"{where}: expected a finite number, got {value!r}")
    if hint is int and not isinstance(value, numbers.Integral):
        raise FieldError(f"{where}: expected an integer, got {value!r}")
    if hint is str and not isinstance(value, str):
        raise FieldError(f"{where}: expected a string, got {value!r}")
    if get_origin(hint) is Literal and value not in get_args(hint):
        raise FieldError(f"{where}: expected one of {list(get_args(hint))}, got {value!r}")


def require(
    obj: Any,
    where: str,
    *,
    at_least_one: tuple[str, ...] = (),
    positive: tuple[str, ...] = (),
    non_negative: tuple[str, ...] = (),
    fraction: tuple[str, ...] = (),
    unit: tuple[str, ...] = (),
) -> None:
    """Range checks of numeric fields of ``obj`` (a table named ``where``): counts >= 1, values
    > 0 or >= 0, fractions in [0, 1) and in [0, 1]."""
    for name in at_least_one:
        if getattr(obj, name) < 1:
            raise ConfigError(f"{where}.{name} must be >= 1, got {getattr(obj, name)}")
    for name in positive:
        if not getattr(obj, name) > 0.0:
            raise ConfigError(f"{where}.{name} must be > 0, got {getattr(obj, name)}")
    for name in non_negative:
        if not getattr(obj, name) >= 0.0:
            raise ConfigError(f"{where}.{name} must be >= 0, got {getattr(obj, name)}")
    for name in fraction:
        if not 0.0 <= getattr(obj, name) < 1.0:
            raise ConfigError(f"{where}.{name} must be in [0, 1), got {getattr(obj, name)}")
    for name in unit:
        if not 0.0 <= getattr(obj, name) <= 1.0:
            raise ConfigError(f"{where}.{name} must be in [0, 1], got {getattr(obj, name)}")


def check_known(cls: type, raw: dict[str, Any], where: str) -> None:
    known = {f.name for f in fields(cls)}
    unknown = set(raw) - known
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; known: {sorted(known)}")


def build(cls: type, raw: dict[str, Any], where: str) -> Any:
    """``cls(**raw)`` from a file's table named ``where``: unknown keys and values that do not
    fit their annotations are a :class:`ConfigError` naming the key."""
    check_known(cls, raw, where)
    try:
        return cls(**raw)
    except FieldError as exc:
        raise ConfigError(f"{where}.{exc}") from None
    except TypeError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def with_numeric_overrides(obj: Any, overrides: dict[str, Any], where: str) -> Any:
    """A copy of the dataclass ``obj`` with some numeric fields changed, as read from a file's
    table named ``where``: unknown keys and non-numbers are :class:`ConfigError`."""
    check_known(type(obj), overrides, where)
    for key, value in overrides.items():
        check_value(float, value, f"{where}.{key}")
    return replace(obj, **{k: float(v) for k, v in overrides.items()})
