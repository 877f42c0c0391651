"""Export range-error models to ONNX and check the export against torch (needs ``relloc[train]``).

The graph takes the raw window ``(batch, n_steps, 3)`` (batch dynamic) and returns two outputs,
``residual`` (the predicted error around the pair's constant) and ``sigma`` (the standard
deviation of what remains), each ``(batch, 1)`` in metres; features and normalisation are inside
it. We use PyTorch's TorchScript
-based exporter (``dynamo=False``): it writes ``nn.LSTM`` as one ONNX ``LSTM`` node, which
onnxruntime runs fast on one core, keeps the batch axis dynamic, and needs no package beyond
``onnx``. Every export is verified by running onnxruntime on random windows.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relloc.ranging.inference import INPUT_NAME, OUTPUT_NAMES
from relloc.ranging.manifest import read_manifest, write_manifest
from relloc.ranging.models import Architecture, EnsembleModel, RangeErrorModel

Exportable = RangeErrorModel | EnsembleModel

OPSET = 17


def onnx_bytes(model: Exportable) -> bytes:
    """Serialise ``model`` (switched to eval mode) to ONNX."""
    model.eval()
    example = torch.zeros(1, model.n_steps, 3)
    example[..., 0] = 3.0
    buf = io.BytesIO()
    with warnings.catch_warnings():
        # The TorchScript exporter warns about its own deprecation and about tracing nn.LSTM's
        # shape checks; neither affects this graph (checked by verify_onnx on every export).
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model,
            (example,),
            buf,  # type: ignore[arg-type]  # annotated as a path, takes a file too
            dynamo=False,
            input_names=[INPUT_NAME],
            output_names=list(OUTPUT_NAMES),
            dynamic_axes={INPUT_NAME: {0: "batch"}, **{n: {0: "batch"} for n in OUTPUT_NAMES}},
            opset_version=OPSET,
        )
    return buf.getvalue()


def verify_onnx(
    model: Exportable, onnx_model: bytes, windows: np.ndarray | None = None, seed: int = 0
) -> float:
    """Largest absolute difference between torch and onnxruntime outputs (both outputs, m).

    ``windows`` default: 64 random windows with plausible ranges and yaws.
    """
    import onnxruntime as ort

    if windows is None:
        rng = np.random.default_rng(seed)
        windows = np.stack(
            [
                rng.uniform(0.5, 8.0, (64, model.n_steps)),
                rng.uniform(-np.pi, np.pi, (64, model.n_steps)),
                rng.uniform(-np.pi, np.pi, (64, model.n_steps)),
            ],
            axis=-1,
        )
    windows = np.asarray(windows, dtype=np.float32)
    model.eval()
    with torch.no_grad():
        expected = np.concatenate([o.numpy() for o in model(torch.from_numpy(windows))], axis=1)
    session = ort.InferenceSession(onnx_model, providers=["CPUExecutionProvider"])
    got = np.concatenate(session.run(list(OUTPUT_NAMES), {INPUT_NAME: windows}), axis=1)
    return float(np.max(np.abs(got - expected))) if len(windows) else 0.0


def save_checkpoint(model: Exportable, path: str | Path) -> None:
    """Torch weights and shape, enough to rebuild and re-export the model (or ensemble)."""
    members = len(model.members) if isinstance(model, EnsembleModel) else 0
    torch.save(
        {
            "architecture": model.arch.to_dict(),
            "n_steps": model.n_steps,
            "members": members,
            "state": model.state_dict(),
        },
        path,
    )


def load_checkpoint(path: str | Path) -> Exportable:
    """Rebuild a model saved by :func:`save_checkpoint` (an ensemble if it was one)."""
    data: dict[str, Any] = torch.load(path, map_location="cpu", weights_only=True)
    arch, n_steps = Architecture.from_dict(data["architecture"]), int(data["n_steps"])
    members = int(data.get("members", 0))
    model: Exportable
    if members:
        model = EnsembleModel([RangeErrorModel(arch, n_steps) for _ in range(members)])
    else:
        model = RangeErrorModel(arch, n_steps)
    model.load_state_dict(data["state"])
    return model.eval()


def export_model(model: Exportable, path: str | Path, tolerance: float = 1e-5) -> float:
    """Write ``model`` as ONNX to ``path`` after checking it; returns the torch/ONNX max diff.

    Raises ``RuntimeError`` if onnxruntime disagrees with torch by more than ``tolerance`` m.
    """
    data = onnx_bytes(model)
    diff = verify_onnx(model, data)
    if not diff <= tolerance:
        raise RuntimeError(f"ONNX export of {path} differs from torch by {diff:.3g} m")
    Path(path).write_bytes(data)
    return diff


def reexport_dir(path: str | Path, tolerance: float = 1e-5) -> dict[str, float]:
    """Re-export every pair of a model directory from its checkpoints; returns max diffs."""
    path = Path(path)
    manifest = read_manifest(path)
    diffs: dict[str, float] = {}
    for pair, entry in manifest["pairs"].items():
        checkpoint = entry.get("checkpoint")
        if not checkpoint or not (path / checkpoint).is_file():
            raise FileNotFoundError(f"{path}: pair {pair} has no torch checkpoint to export from")
        model = load_checkpoint(path / checkpoint)
        diffs[pair] = export_model(model, path / entry["onnx"], tolerance)
        entry["onnx_max_diff"] = diffs[pair]
    manifest.pop("format", None)
    write_manifest(path, manifest)
    return diffs
