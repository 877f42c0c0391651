"""Run trained range-error models with onnxruntime (NumPy only, no torch).

:class:`ModelSet` loads a model directory (see :mod:`relloc.ranging.manifest`) into one
:class:`PairModel` per UWB node pair. A pair model takes raw windows ``[range, yaw_a, yaw_b]``
(canonical node order, metres and radians) and returns the predicted ranging error in metres,
clipped to the range of errors seen in training: a model asked about an input unlike anything
it was trained on must not move a range further than the training data ever did.

Each ONNX session runs on one thread (``intra_op_num_threads=1``): one window is tiny, thread
hand-offs would cost more than they save, and the filter runs beside it.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from relloc.ranging.manifest import ModelDirError, read_manifest

INPUT_NAME = "window"


def session_options(threads: int = 1) -> ort.SessionOptions:
    """onnxruntime options for small sequential models on ``threads`` threads."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return options


class PairModel:
    """The range-error model of one node pair."""

    def __init__(
        self,
        pair: str,
        nodes: tuple[str, str],
        n_steps: int,
        onnx_model: str | Path | bytes,
        *,
        error_min: float = -np.inf,
        error_max: float = np.inf,
        threads: int = 1,
    ) -> None:
        self.pair = pair
        self.nodes = nodes
        self.n_steps = n_steps
        self.error_min = error_min
        self.error_max = error_max
        source = onnx_model if isinstance(onnx_model, bytes) else str(onnx_model)
        self.session = ort.InferenceSession(
            source, session_options(threads), providers=["CPUExecutionProvider"]
        )
        self._input = self.session.get_inputs()[0].name

    def predict_raw(self, windows: np.ndarray) -> np.ndarray:
        """Unclipped predicted errors ``(B,)`` for windows ``(B, n_steps, 3)`` (m)."""
        windows = np.asarray(windows, dtype=np.float32)
        if windows.ndim != 3 or windows.shape[1:] != (self.n_steps, 3):
            raise ValueError(
                f"{self.pair}: windows must have shape (B, {self.n_steps}, 3), got {windows.shape}"
            )
        out = self.session.run(None, {self._input: windows})[0]
        return np.asarray(out, dtype=np.float64).reshape(-1)

    def predict(self, windows: np.ndarray) -> np.ndarray:
        """Predicted errors ``(B,)`` clipped to the training errors' range (m)."""
        return np.clip(self.predict_raw(windows), self.error_min, self.error_max)


class ModelSet(Mapping[str, PairModel]):
    """All pair models of one trained-model directory, keyed by node pair (``"n_3-n_7"``)."""

    def __init__(self, directory: Path, manifest: dict[str, Any], models: dict[str, PairModel]):
        self.directory = directory
        self.manifest = manifest
        self._models = models

    @classmethod
    def load(cls, path: str | Path, threads: int = 1) -> ModelSet:
        """Load every pair of the directory; raises :class:`ModelDirError` if it is not one."""
        path = Path(path)
        manifest = read_manifest(path)
        n_steps = int(manifest["n_steps"])
        models: dict[str, PairModel] = {}
        for pair, entry in manifest["pairs"].items():
            nodes = tuple(entry["nodes"])
            if len(nodes) != 2:
                raise ModelDirError(f"{path}: pair {pair!r} must name two nodes, got {nodes}")
            try:
                models[pair] = PairModel(
                    pair,
                    (str(nodes[0]), str(nodes[1])),
                    n_steps,
                    path / entry["onnx"],
                    error_min=float(entry.get("error_min", -np.inf)),
                    error_max=float(entry.get("error_max", np.inf)),
                    threads=threads,
                )
            except (ort.capi.onnxruntime_pybind11_state.Fail, RuntimeError) as exc:  # type: ignore[attr-defined]
                raise ModelDirError(
                    f"{path / entry['onnx']}: onnxruntime cannot load it: {exc}"
                ) from None
        return cls(path, manifest, models)

    @property
    def variant(self) -> str:
        return str(self.manifest["variant"])

    @property
    def n_steps(self) -> int:
        return int(self.manifest["n_steps"])

    @property
    def name(self) -> str:
        """Short label for reports: the variant."""
        return self.variant

    def __getitem__(self, pair: str) -> PairModel:
        return self._models[pair]

    def __iter__(self) -> Iterator[str]:
        return iter(self._models)

    def __len__(self) -> int:
        return len(self._models)
