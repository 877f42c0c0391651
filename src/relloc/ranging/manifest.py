"""The trained-model directory: one ONNX file per node pair and a JSON manifest.

Layout (written by ``relloc ranging train``, read by evaluation and the run-time stage)::

    DIR/
      manifest.json        # this module's schema, below
      n_3-n_7.onnx         # raw window (B, n_steps, 3) -> residual, sigma (B, 1), metres
      n_3-n_7.pt           # torch checkpoint, only for `relloc ranging export` (re-export)
      ...

``manifest.json``::

    {
      "format": "relloc-ranging/2",
      "variant": "stacked", "n_steps": 10,
      "offset": "manifest",                       # run time: add train_bias, or "filter"
      "constant": 0.32,                           # mean error over every pair (a baseline)
      "architecture": {"variant": ..., "hidden": [50, 50], "dropout": 0.3, "features": ...},
      "node_map": {"1": "n_7", ...},
      "training": {"csv": ..., "csv_sha256": ..., "split": [0.7, 0.1, 0.2], "seed": 0, ...},
      "pairs": {
        "n_3-n_7": {
          "nodes": ["n_3", "n_7"], "onnx": "n_3-n_7.onnx", "checkpoint": "n_3-n_7.pt",
          "normalisation": {"feature_mean": [...], "feature_scale": [...],
                            "target_mean": ..., "target_std": ...},
          "train_bias": ...,                      # the pair's constant: mean error of the
                                                  # rows before the test part (the offset)
          "residual_min": ..., "residual_max": ..., # training residuals (run-time clip)
          "fallback": false,                      # guard: true = apply the constant only
          "fallback_sigma": ...,                  # the constant's validation RMSE
          "test_rows": [start, stop], "val_blocks": [[start, stop], ...],
          "val_mse": ..., "val_mse_bias": ..., "epochs": ..., "best_epoch": ..., ...
        }, ...
      }
    }

The model predicts the *residual* around the pair's constant; the predicted error is
``train_bias + clip(residual, residual_min, residual_max)`` (or ``train_bias`` alone for a
``fallback`` pair). The normalisation is also baked into each ONNX graph (the manifest copy is
for people and for checks); the frames are ``[range, yaw_a, yaw_b]`` with ``a`` the node that
sorts first. Directories of the first format (models of the full error) must be retrained.
No torch here.
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
    if not isinstance(data["pairs"], dict) or not all(isinstance(e, dict) for e in data["pairs"].values()):
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
