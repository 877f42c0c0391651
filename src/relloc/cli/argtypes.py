"""``argparse`` types for the flags every command shares: a bad value is argparse's one-line
usage error (exit 2), never a traceback from NumPy later or a value silently ignored."""

from __future__ import annotations

import argparse
import math


def seed(text: str) -> int:
    """A random seed: an integer >= 0 (NumPy's generators take no negative seed)."""
    value = int(_parse(int, text))
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def seeds(text: str) -> list[int]:
    """Seeds for a sweep: ``LO-HI`` (both included) or a comma-separated list, each a :func:`seed`."""
    if "-" in text:
        lo, hi = (seed(part) for part in text.split("-", 1))
        if hi < lo:
            raise argparse.ArgumentTypeError(f"empty range {text!r}")
        return list(range(lo, hi + 1))
    return [seed(part) for part in text.split(",")]


def count(text: str) -> int:
    """A count of things (particles): an integer >= 1."""
    value = int(_parse(int, text))
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def positive(text: str) -> float:
    """A duration, a rate, a period: a finite number > 0."""
    value = float(_parse(float, text))
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def non_negative(text: str) -> float:
    """A finite number >= 0 (a window that may be zero)."""
    value = float(_parse(float, text))
    if not (math.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def span(text: str) -> tuple[float, float]:
    """``START:END`` seconds from a recording's start (:func:`relloc.sources.span.parse_span`)."""
    from relloc.sources.span import parse_span

    try:
        return parse_span(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _parse(kind: type[int] | type[float], text: str) -> int | float:
    try:
        return kind(text)
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
