"""Registry of the sub-commands that live beside the core CLI, each in its own module.

Each module exposes ``register(subparsers)``. None of them imports an optional dependency at
module level (the training commands import torch only when they run), so every command is
always listed; a module that fails to import is a bug and raises.
"""

from __future__ import annotations

import argparse
import importlib

_MODULES = ("relloc.ranging.cli", "relloc.live.cli", "relloc.bench_resources", "relloc.navigation.cli")


def register_all(sub: argparse._SubParsersAction) -> None:
    for name in _MODULES:
        importlib.import_module(name).register(sub)
