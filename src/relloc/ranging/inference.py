"""Run trained range-error models with onnxruntime (NumPy only, no torch).

:class:`ModelSet` loads a model directory (see :mod:`relloc.ranging.manifest`) into one
:class:`PairModel` per UWB node pair. A pair model takes raw windows ``[range, yaw_a, yaw_b]``
(canonical node order, metres and radians) and returns the predicted ranging error in metres
with its standard deviation:

* error = the pair's constant (``offset``, the manifest's ``train_bias``) + the model's
  residual, clipped to the residuals seen in training: a model asked about an input unlike
  anything it was trained on must not move a range further than the training data ever did;
* sigma = the model's learned standard deviation of what remains;
* a pair the training guard marked ``fallback`` (its model did not clearly beat the constant
  on the validation blocks) gets the constant alone, with the constant's validation RMSE as
  the sigma, and its ONNX model is never run.

Each ONNX session runs on one thread (``intra_op_num_threads=1``): one window is tiny, thread
hand-offs would cost more than they save, and the filter runs beside it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from relloc.ranging.manifest import ModelDirError, read_manifest
from relloc.ranging.support import InputSupport

INPUT_NAME = "window"
OUTPUT_NAMES = ("residual", "sigma")
OFFSET_MODES = ("manifest", "filter")
"""How the run time applies a pair's constant: ``manifest`` adds it (the range leaves the stage
``corrected``), ``filter`` leaves it to the filter's own pair bias (calibrated or online)."""


def session_options(threads: int = 1) -> ort.SessionOptions:
    """onnxruntime options for small sequential models on ``threads`` threads."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return options


class PairModel:
    """The range-error model of one node pair: constant + clipped learned residual, and sigma."""

    def __init__(
        self,
        pair: str,
        nodes: tuple[str, str],
        n_steps: int,
        onnx_model: str | Path | bytes,
        *,
        offset: float = 0.0,
        residual_min: float = -np.inf,
        residual_max: float = np.inf,
        fallback: bool = False,
        fallback_sigma: float | None = None,
        threads: int = 1,
        support: InputSupport | None = None,
    ) -> None:
        if n_steps < 1:
            raise ValueError(f"{pair}: n_steps must be >= 1, got {n_steps}")
        if not residual_min < residual_max:
            raise ValueError(
                f"{pair}: residual_min {residual_min} must be below residual_max {residual_max}"
            )
        if not math.isfinite(offset):
            raise ValueError(f"{pair}: offset {offset} is not finite")
        if fallback and not (fallback_sigma is not None and fallback_sigma > 0):
            raise ValueError(f"{pair}: a fallback pair needs a positive fallback_sigma")
        self.pair = pair
        self.nodes = nodes
        self.n_steps = n_steps
        self.offset = float(offset)
        self.residual_min = residual_min
        self.residual_max = residual_max
        self.fallback = fallback
        self.fallback_sigma = fallback_sigma
        self.support = support
        """Where the model was trained (:mod:`relloc.ranging.support`); ``None``: no guard."""
        source = onnx_model if isinstance(onnx_model, bytes) else str(onnx_model)
        self.session = ort.InferenceSession(
            source, session_options(threads), providers=["CPUExecutionProvider"]
        )
        inputs = self.session.get_inputs()
        shape = list(inputs[0].shape) if len(inputs) == 1 else []
        fixed = [d if isinstance(d, int) else None for d in shape]
        if len(shape) != 3 or fixed[1:] not in (
            [n_steps, 3],
            [None, 3],
            [n_steps, None],
            [None, None],
        ):
            raise ValueError(
                f"{pair}: the model takes {[i.shape for i in inputs]}, not (B, {n_steps}, 3)"
            )
        if inputs[0].type != "tensor(float)":
            raise ValueError(f"{pair}: the model takes {inputs[0].type}, not float32 windows")
        outputs = [o.name for o in self.session.get_outputs()]
        if outputs != list(OUTPUT_NAMES):
            raise ValueError(f"{pair}: the model answers {outputs}, not {list(OUTPUT_NAMES)}")
        self._input = inputs[0].name
        try:  # one window in, one residual and one sigma out: otherwise it is not ours
            probe = self.session.run(None, {self._input: np.zeros((1, n_steps, 3), np.float32)})
        except Exception as exc:
            raise ValueError(
                f"{pair}: the model cannot run on a (1, {n_steps}, 3) window: {exc}"
            ) from None
        if any(np.size(p) != 1 for p in probe):
            raise ValueError(
                f"{pair}: the model answers {[np.shape(p) for p in probe]} for one window, "
                "not one residual and one sigma"
            )

    def predict_raw(self, windows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The model's unclipped residuals and sigmas ``(B,)`` for windows ``(B, n_steps, 3)``."""
        windows = np.asarray(windows, dtype=np.float32)
        if windows.ndim != 3 or windows.shape[1:] != (self.n_steps, 3):
            raise ValueError(
                f"{self.pair}: windows must have shape (B, {self.n_steps}, 3), got {windows.shape}"
            )
        residual, sigma = self.session.run(None, {self._input: windows})
        return (
            np.asarray(residual, dtype=np.float64).reshape(-1),
            np.asarray(sigma, dtype=np.float64).reshape(-1),
        )

    def clip(self, residual: np.ndarray) -> np.ndarray:
        """Residuals clipped to the training residuals' range."""
        return np.clip(residual, self.residual_min, self.residual_max)

    def predict_residual(self, windows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(residual, sigma)`` ``(B,)``: what the stage removes beside the offset (m).

        Clipped residuals and the model's sigma; for a ``fallback`` pair zeros and the
        constant's validation RMSE (the model is not run).
        """
        n = len(windows)
        if self.fallback:
            return np.zeros(n), np.full(n, float(self.fallback_sigma))  # type: ignore[arg-type]
        residual, sigma = self.predict_raw(windows)
        return self.clip(residual), sigma

    def predict(self, windows: np.ndarray) -> np.ndarray:
        """Predicted errors ``(B,)``: the pair's constant plus the clipped residual (m)."""
        return self.offset + self.predict_residual(windows)[0]


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
            raise ModelDirError(
                f"{path}: malformed manifest ({type(exc).__name__}: {exc})"
            ) from None
        if not entries:
            raise ModelDirError(f"{path}: the manifest lists no pair")
        if manifest.get("offset", "manifest") not in OFFSET_MODES:
            raise ModelDirError(
                f"{path}: offset {manifest.get('offset')!r} is not one of {OFFSET_MODES}"
            )
        for pair, entry in entries.items():
            try:
                nodes = tuple(entry["nodes"])
                onnx_file = path / entry["onnx"]
                offset = float(entry["train_bias"])
                residual_min = float(entry["residual_min"])
                residual_max = float(entry["residual_max"])
                fallback = bool(entry.get("fallback", False))
                fb_sigma = entry.get("fallback_sigma")
                fallback_sigma = None if fb_sigma is None else float(fb_sigma)
                support = InputSupport.from_json(entry["support"]) if "support" in entry else None
            except (KeyError, TypeError, ValueError, AttributeError) as exc:
                raise ModelDirError(
                    f"{path}: pair {pair!r}: malformed entry ({type(exc).__name__}: {exc})"
                ) from None
            if len(nodes) != 2:
                raise ModelDirError(f"{path}: pair {pair!r} must name two nodes, got {nodes}")
            try:
                models[pair] = PairModel(
                    pair,
                    (str(nodes[0]), str(nodes[1])),
                    n_steps,
                    onnx_file,
                    offset=offset,
                    residual_min=residual_min,
                    residual_max=residual_max,
                    fallback=fallback,
                    fallback_sigma=fallback_sigma,
                    threads=threads,
                    support=support,
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
    def offset_mode(self) -> str:
        """``manifest`` (the stage adds each pair's constant) or ``filter`` (leaves it)."""
        return str(self.manifest.get("offset", "manifest"))

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
