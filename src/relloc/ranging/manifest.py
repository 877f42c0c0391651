"""The trained-model directory: one ONNX file per node pair and a JSON manifest.

The derivation: docs/explanation/internals.md, section ``relloc.ranging.manifest``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

MANIFEST_NAME = "manifest.json"
FORMAT = "relloc-ranging/2"


class ModelDirError(ValueError):
    """A trained-model directory is missing, incomplete or of an unknown format."""


def is_model_dir(path: str | Path) -> bool:
    """True if ``path`` holds a manifest."""
    return (Path(path) / MANIFEST_NAME).is_file()


def read_manifest(path: str | Path) -> dict[str, Any]:
    """Load and check ``DIR/manifest.json``; raises :class:`ModelDirError` with the reason."""
    path = Path(path)
    file = path / MANIFEST_NAME
    try:
        data = json.loads(file.read_text())
    except FileNotFoundError:
        raise ModelDirError(
            f"{path}: no {MANIFEST_NAME}; is this a trained model directory?"
        ) from None
    except json.JSONDecodeError as exc:
        raise ModelDirError(f"{file}: not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ModelDirError(f"{file}: expected a JSON object, got {type(data).__name__}")
    if data.get("format") != FORMAT:
        raise ModelDirError(
            f"{file}: format {data.get('format')!r}, expected {FORMAT!r}; retrain with "
            "`relloc ranging train`"
        )
    for key in ("variant", "n_steps", "pairs"):
        if key not in data:
            raise ModelDirError(f"{file}: missing key {key!r}")
    if not isinstance(data["pairs"], dict) or not all(
        isinstance(e, dict) for e in data["pairs"].values()
    ):
        raise ModelDirError(f"{file}: 'pairs' must map each node pair to an object")
    for pair, entry in data["pairs"].items():
        for key in ("nodes", "onnx"):
            if key not in entry:
                raise ModelDirError(f"{file}: pair {pair!r} has no {key!r}")
        if not (path / entry["onnx"]).is_file():
            raise ModelDirError(f"{file}: pair {pair!r}: {entry['onnx']} is missing")
    return data


def write_manifest(path: str | Path, manifest: dict[str, Any]) -> Path:
    """Write ``DIR/manifest.json`` (pretty, stable key order) and return its path."""
    file = Path(path) / MANIFEST_NAME
    file.write_text(json.dumps({"format": FORMAT, **manifest}, indent=2) + "\n")
    return file


def find_model_dirs(paths: list[str | Path]) -> list[Path]:
    """Model directories named by ``paths``: each one itself, or its sub-directories that are.

    Lets ``--models models/ranging`` evaluate every variant trained under it.
    """
    found: list[Path] = []
    for p in map(Path, paths):
        if is_model_dir(p):
            found.append(p)
            continue
        if not p.is_dir():
            raise ModelDirError(f"{p}: not a directory")
        subs = sorted(d for d in p.iterdir() if d.is_dir() and is_model_dir(d))
        if not subs:
            raise ModelDirError(f"{p}: neither a model directory nor a parent of any")
        found.extend(subs)
    return found
