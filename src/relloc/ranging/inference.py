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
        if n_steps < 1:
            raise ValueError(f"{pair}: n_steps must be >= 1, got {n_steps}")
        if not error_min < error_max:
            raise ValueError(f"{pair}: error_min {error_min} must be below error_max {error_max}")
        self.pair = pair
        self.nodes = nodes
        self.n_steps = n_steps
        self.error_min = error_min
        self.error_max = error_max
        source = onnx_model if isinstance(onnx_model, bytes) else str(onnx_model)
        self.session = ort.InferenceSession(
            source, session_options(threads), providers=["CPUExecutionProvider"]
        )
        inputs = self.session.get_inputs()
        shape = list(inputs[0].shape) if len(inputs) == 1 else []
        fixed = [d if isinstance(d, int) else None for d in shape]
        if len(shape) != 3 or fixed[1:] not in ([n_steps, 3], [None, 3], [n_steps, None], [None, None]):
            raise ValueError(f"{pair}: the model takes {[i.shape for i in inputs]}, not (B, {n_steps}, 3)")
        if inputs[0].type != "tensor(float)":
            raise ValueError(f"{pair}: the model takes {inputs[0].type}, not float32 windows")
        self._input = inputs[0].name
        try:  # one window in, one error out: a model that answers otherwise is not ours
            probe = self.session.run(None, {self._input: np.zeros((1, n_steps, 3), np.float32)})[0]
        except Exception as exc:
            raise ValueError(f"{pair}: the model cannot run on a (1, {n_steps}, 3) window: {exc}") from None
        if np.size(probe) != 1:
            raise ValueError(f"{pair}: the model answers {np.shape(probe)} for one window, not one error")

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
        models: dict[str, PairModel] = {}
        try:
            n_steps = int(manifest["n_steps"])
            entries = dict(manifest["pairs"].items())
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ModelDirError(f"{path}: malformed manifest ({type(exc).__name__}: {exc})") from None
        if not entries:
            raise ModelDirError(f"{path}: the manifest lists no pair")
        for pair, entry in entries.items():
            try:
                nodes = tuple(entry["nodes"])
                onnx_file = path / entry["onnx"]
                error_min = float(entry.get("error_min", -np.inf))
                error_max = float(entry.get("error_max", np.inf))
            except (KeyError, TypeError, ValueError, AttributeError) as exc:
                raise ModelDirError(f"{path}: pair {pair!r}: malformed entry ({type(exc).__name__}: {exc})") from None
            if len(nodes) != 2:
                raise ModelDirError(f"{path}: pair {pair!r} must name two nodes, got {nodes}")
            try:
                models[pair] = PairModel(
                    pair,
                    (str(nodes[0]), str(nodes[1])),
                    n_steps,
                    onnx_file,
                    error_min=error_min,
                    error_max=error_max,
                    threads=threads,
                )
            except ValueError as exc:
                raise ModelDirError(f"{path}: {exc}") from None
            except Exception as exc:  # onnxruntime's own exception types vary by failure
                raise ModelDirError(f"{onnx_file}: onnxruntime cannot load it: {exc}") from None
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
