"""Registry of the sub-commands that live beside the core CLI (ranging, run, calibrate, ...).

Each module exposes ``register(subparsers)``; a module whose optional dependencies are missing
is skipped, so the core CLI always works.
"""

from __future__ import annotations

import argparse
import importlib

_MODULES = ("relloc.ranging.cli", "relloc.live", "relloc.navigation.cli")


def register_all(sub: argparse._SubParsersAction) -> None:
    for name in _MODULES:
        try:
            module = importlib.import_module(name)
        except ImportError:
            continue
        module.register(sub)
