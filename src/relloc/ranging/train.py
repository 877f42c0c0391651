"""Train one range-error model per UWB node pair (needs ``relloc[train]``).

What is learnt, and what is not. A pair's ranging error is a constant (its bias) plus a part
that depends on how the antennas are turned and on recent motion. The constant moves between
sessions (the per-pair biases of one day are worse than one shared constant on another, see
docs/explanation/range-correction.md); the orientation- and motion-dependent part should not. So each model learns
only the **residual around the pair's constant** (``error - train_bias``, with ``train_bias``
the median error of the rows before the test part: the statistic of a pair calibration, so a
pair that falls back gets what ``relloc calibrate`` would give), and the constant is stored
in the manifest: the run time adds it back, or leaves the offset to the filter
(``TrainConfig.offset``), and evaluation can estimate it online.

The derivation: docs/explanation/internals.md, section ``relloc.ranging.train``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from relloc.ranging.dataset import (
    DEFAULT_NODE_MAP,
    DEFAULT_SPLIT,
    DEFAULT_VAL_BLOCKS,
    BlockSplit,
    PairSeries,
    RangingDataError,
    block_split,
    drop_repeats,
    file_sha256,
    load_csv,
    make_windows,
    split_bounds,
)
from relloc.ranging.export import export_model, save_checkpoint
from relloc.ranging.inference import OFFSET_MODES
from relloc.ranging.manifest import write_manifest
from relloc.ranging.models import (
    Architecture,
    EnsembleModel,
    Normalisation,
    RangeErrorModel,
    build_model,
)
from relloc.ranging.support import InputSupport


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (the architecture is :class:`~relloc.ranging.models.Architecture`)."""

    n_steps: int = 10
    """Frames per window (repeat-free UWB samples, about 1.5 s at 7 Hz)."""
    epochs: int = 150
    """Upper bound on epochs; early stopping usually ends sooner."""
    patience: int = 15
    """Stop after this many epochs without a better validation MSE."""
    batch_size: int = 32
    lr: float = 1e-3
    weight_decay: float = 1e-4
    """AdamW decoupled weight decay: a little regularisation for one short session."""
    seed: int = 0
    split: tuple[float, float, float] = DEFAULT_SPLIT
    """Fractions of the rows: train, validation (in blocks), test (the last rows)."""
    val_blocks: int = DEFAULT_VAL_BLOCKS
    """Validation blocks, spread over the rows before the test part."""
    val_gap: int | None = None
    """Rows left out of training on each side of a validation block and before the test part;
    None: ``n_steps``."""
    guard_margin: float = 0.1
    """A model must beat the constant's validation MSE by this fraction, else it falls back."""
    ensemble: int = 1
    """Members per pair, trained from different seeds (spread adds to the sigma)."""
    offset: str = "manifest"
    """Run-time offset: ``manifest`` (add the pair's constant, the range is ``corrected``) or
    ``filter`` (remove only the residual; the filter applies its own pair bias, calibrated or
    estimated online)."""

    def __post_init__(self) -> None:
        if self.n_steps < 1 or self.epochs < 1 or self.patience < 1 or self.batch_size < 1:
            raise ValueError(f"n_steps, epochs, patience and batch_size must be >= 1: {self}")
        if self.val_blocks < 1:
            raise ValueError(f"val_blocks must be >= 1, got {self.val_blocks}")
        if self.ensemble < 1:
            raise ValueError(f"ensemble must be >= 1, got {self.ensemble}")
        if self.val_gap is not None and self.val_gap < 0:
            raise ValueError(f"val_gap must be >= 0, got {self.val_gap}")
        if not 0.0 <= self.guard_margin < 1.0:
            raise ValueError(f"guard_margin must be in [0, 1), got {self.guard_margin}")
        if self.offset not in OFFSET_MODES:
            raise ValueError(f"offset must be one of {OFFSET_MODES}, got {self.offset!r}")
        split_bounds(100, self.split)  # validates the fractions


@dataclass
class PairReport:
    """What training one pair did (stored in the manifest and printed)."""

    pair: str
    n_rows: int
    repeats_dropped: int
    n_train: int
    n_val: int
    n_test: int
    epochs: int
    best_epoch: list[int]
    val_mse: float
    val_mse_bias: float
    val_mse_zero: float
    train_bias: float
    fallback: bool
    train_time_s: float


Progress = Callable[[str, int, int, float], None]
"""``progress(pair, epoch, max_epochs, val_mse)`` after each epoch."""


def _as_tensor(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))


def _seed_for(seed: int, pair: str) -> int:
    """A per-pair seed independent of the other pairs in the file."""
    return (seed * 1_000_003 + sum((i + 1) * ord(c) for i, c in enumerate(pair))) % (2**31)


def fit_normalisation(
    model: RangeErrorModel, windows: np.ndarray, errors: np.ndarray
) -> Normalisation:
    """Feature mean/std over every frame of the training windows; target mean/std."""
    with torch.no_grad():
        feats = model.transform.raw(_as_tensor(windows)).reshape(-1, model.arch.n_features)
    mean = feats.mean(dim=0)
    std = feats.std(dim=0, unbiased=False)
    target_std = float(np.std(errors))
    return Normalisation(
        feature_mean=tuple(float(v) for v in mean),
        feature_std=tuple(float(v) for v in std),
        target_mean=float(np.mean(errors)),
        target_std=target_std if target_std > 1e-6 else 1.0,
    )


def train_model(
    train: tuple[np.ndarray, np.ndarray],
    val: tuple[np.ndarray, np.ndarray],
    arch: Architecture,
    config: TrainConfig,
    *,
    seed: int | None = None,
    on_epoch: Callable[[int, float], None] | None = None,
) -> tuple[RangeErrorModel, dict[str, Any]]:
    """Train one model on ``(windows, targets)`` with early stopping on ``val``.

    The loss is the MSE of the normalised target plus the Gaussian negative log-likelihood of
    the uncertainty head on the detached residuals (it trains that head only). After training
    the sigma is scaled so that ``mean((residual / sigma)^2) = 1`` on ``val``.

    Returns the model with its best weights (eval mode) and ``{"epochs", "best_epoch",
    "val_mse", "sigma_scale"}`` (validation MSE in m^2 of the best weights).
    """
    train_w, train_y = train
    val_w, val_y = val
    if len(train_w) == 0 or len(val_w) == 0:
        raise RangingDataError(
            f"too few samples to train: {len(train_w)} training and {len(val_w)} validation "
            f"windows of {config.n_steps} frames"
        )
    seed = config.seed if seed is None else seed
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = build_model(arch, config.n_steps)
    norm = fit_normalisation(model, train_w, train_y)
    model.set_normalisation(norm)
    x, y = _as_tensor(train_w), _as_tensor((train_y - norm.target_mean) / norm.target_std)
    xv, yv = _as_tensor(val_w), _as_tensor(val_y)
    optimiser = torch.optim.AdamW(
        model.parameters(), lr=config.lr, weight_decay=config.weight_decay
    )

    def val_mse() -> float:
        model.eval()
        with torch.no_grad():
            return float(torch.mean((model(xv)[0][:, 0] - yv) ** 2))

    best = val_mse()
    best_state = {k: v.clone() for k, v in model.state_dict().items()}
    best_epoch, epoch = 0, 0
    for epoch in range(1, config.epochs + 1):
        model.train()
        order = rng.permutation(len(x))
        for start in range(0, len(order), config.batch_size):
            idx = torch.from_numpy(order[start : start + config.batch_size])
            optimiser.zero_grad()
            mu, sigma = model.forward_normalised(x[idx])
            mu, sigma = mu[:, 0], sigma[:, 0]
            residual = (y[idx] - mu).detach()
            nll = torch.mean(0.5 * (residual / sigma) ** 2 + torch.log(sigma))
            loss = torch.mean((mu - y[idx]) ** 2) + nll
            loss.backward()
            nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            optimiser.step()
        current = val_mse()
        if current < best:
            best, best_epoch = current, epoch
            best_state = {k: v.clone() for k, v in model.state_dict().items()}
        if on_epoch is not None:
            on_epoch(epoch, current)
        if epoch - best_epoch >= config.patience:
            break
    model.load_state_dict(best_state)
    model.eval()
    with torch.no_grad():
        mu, sigma = model(xv)
        z2 = float(torch.mean(((yv - mu[:, 0]) / sigma[:, 0]) ** 2))
        model.sigma_scale.fill_(float(np.sqrt(z2)) if np.isfinite(z2) and z2 > 0 else 1.0)
    return model, {
        "epochs": epoch,
        "best_epoch": best_epoch,
        "val_mse": best,
        "sigma_scale": float(model.sigma_scale),
    }


def train_ensemble(
    train: tuple[np.ndarray, np.ndarray],
    val: tuple[np.ndarray, np.ndarray],
    arch: Architecture,
    config: TrainConfig,
    *,
    seed: int | None = None,
    on_epoch: Callable[[int, float], None] | None = None,
) -> tuple[EnsembleModel, dict[str, Any]]:
    """``config.ensemble`` members (:func:`train_model`, seeds ``seed + 7919 k``), combined
    and their sigma calibrated on ``val`` again. ``on_epoch`` counts epochs over all members.

    Returns the ensemble and ``{"epochs", "best_epoch", "val_mse", "sigma_scale",
    "member_val_mse"}`` (epochs and best epochs summed and listed per member).
    """
    seed = config.seed if seed is None else seed
    members, infos = [], []
    for k in range(config.ensemble):

        def member_epoch(epoch: int, mse: float, k: int = k) -> None:
            if on_epoch is not None:
                on_epoch(k * config.epochs + epoch, mse)

        member, info = train_model(
            train, val, arch, config, seed=seed + 7919 * k, on_epoch=member_epoch
        )
        members.append(member)
        infos.append(info)
    ensemble = EnsembleModel(members).eval()
    xv, yv = _as_tensor(val[0]), _as_tensor(val[1])
    with torch.no_grad():
        mu, sigma = ensemble(xv)
        val_mse = float(torch.mean((mu[:, 0] - yv) ** 2))
        z2 = float(torch.mean(((yv - mu[:, 0]) / sigma[:, 0]) ** 2))
        ensemble.sigma_scale.fill_(float(np.sqrt(z2)) if np.isfinite(z2) and z2 > 0 else 1.0)
    return ensemble, {
        "epochs": int(sum(i["epochs"] for i in infos)),
        "best_epoch": [int(i["best_epoch"]) for i in infos],
        "val_mse": val_mse,
        "sigma_scale": float(ensemble.sigma_scale),
        "member_val_mse": [float(i["val_mse"]) for i in infos],
    }


@dataclass(frozen=True)
class PairData:
    """One pair's repeat-free rows, their split, the constant and the windows per part."""

    clean: PairSeries
    dropped: int
    split: BlockSplit
    train_bias: float
    """Median error of the rows before the test part: the pair's constant (offset), the
    statistic of a pair calibration (robust to the one-sided NLOS excess a mean follows)."""
    windows: dict[str, tuple[np.ndarray, np.ndarray]]
    """``train``/``val``/``test`` -> ``(windows, residual targets = error - train_bias)``."""


def split_pair(series: PairSeries, config: TrainConfig) -> PairData:
    """Drop repeats, split by blocks of time, de-mean the errors by the pair's constant."""
    clean, dropped = drop_repeats(series)
    gap = config.n_steps if config.val_gap is None else config.val_gap
    split = block_split(len(clean), config.split, config.val_blocks, gap=gap)
    train_bias = float(np.median(clean.error[: split.end_dev])) if split.end_dev else 0.0
    parts: dict[str, np.ndarray | slice] = {
        "train": split.train,
        "val": split.val,
        "test": slice(split.end_dev, len(clean)),
    }
    windows = {}
    for name, rows in parts.items():
        w, e, _ = make_windows(clean, config.n_steps, rows)
        windows[name] = (w, e - train_bias)
    return PairData(clean, dropped, split, train_bias, windows)


def _support(windows: np.ndarray) -> dict[str, Any]:
    """The manifest's ``support`` of a pair's development windows (none without windows)."""
    return {"support": InputSupport.of(windows).to_json()} if len(windows) else {}


def train_directory(
    csv_path: str | Path,
    out: str | Path,
    arch: Architecture,
    config: TrainConfig,
    *,
    node_map: Mapping[str, str] | None = None,
    pairs: Sequence[str] | None = None,
    progress: Progress | None = None,
) -> tuple[dict[str, Any], list[PairReport]]:
    """Train every pair (or ``pairs``) of ``csv_path``; write ONNX files and the manifest to ``out``.

    Returns the manifest and one :class:`PairReport` per pair.
    """
    torch.set_num_threads(1)
    node_map = dict(DEFAULT_NODE_MAP if node_map is None else node_map)
    series = load_csv(csv_path, node_map)
    if pairs:
        unknown = sorted(set(pairs) - set(series))
        if unknown:
            raise RangingDataError(f"pair(s) {unknown} not in {csv_path}; it has {sorted(series)}")
        series = {k: v for k, v in series.items() if k in set(pairs)}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    reports: list[PairReport] = []
    entries: dict[str, Any] = {}
    dev_errors: list[np.ndarray] = []
    for key, s in series.items():
        t0 = time.perf_counter()
        data = split_pair(s, config)
        win = data.windows

        def on_epoch(epoch: int, mse: float, key: str = key) -> None:
            if progress is not None:
                progress(key, epoch, config.epochs * config.ensemble, mse)

        model, info = train_ensemble(
            win["train"],
            win["val"],
            arch,
            config,
            seed=_seed_for(config.seed, key),
            on_epoch=on_epoch,
        )
        val_resid = win["val"][1]
        val_mse_bias = float(np.mean(val_resid**2))
        # Guard: the model must clearly beat the constant on the validation blocks.
        fallback = not info["val_mse"] <= (1.0 - config.guard_margin) * val_mse_bias
        onnx_name, ckpt_name = f"{key}.onnx", f"{key}.pt"
        diff = export_model(model, out / onnx_name)
        save_checkpoint(model, out / ckpt_name)
        report = PairReport(
            pair=key,
            n_rows=len(s),
            repeats_dropped=data.dropped,
            n_train=len(win["train"][1]),
            n_val=len(val_resid),
            n_test=len(win["test"][1]),
            epochs=info["epochs"],
            best_epoch=info["best_epoch"],
            val_mse=info["val_mse"],
            val_mse_bias=val_mse_bias,
            val_mse_zero=float(np.mean((val_resid + data.train_bias) ** 2)),
            train_bias=data.train_bias,
            fallback=fallback,
            train_time_s=time.perf_counter() - t0,
        )
        reports.append(report)
        dev_errors.append(data.clean.error[: data.split.end_dev])
        first = cast(RangeErrorModel, model.members[0])  # members: list[RangeErrorModel]
        norm = first.transform
        train_resid = win["train"][1]
        entries[key] = {
            "nodes": [data.clean.node_a, data.clean.node_b],
            "onnx": onnx_name,
            "checkpoint": ckpt_name,
            "normalisation": {
                "feature_mean": [float(v) for v in norm.mean],
                "feature_scale": [float(v) for v in norm.scale],
                "target_mean": float(first.target_mean),
                "target_std": float(first.target_std),
            },
            "residual_min": float(np.min(train_resid)),
            "residual_max": float(np.max(train_resid)),
            "fallback_sigma": float(np.sqrt(val_mse_bias)),
            **_support(np.concatenate([win["train"][0], win["val"][0]])),
            "sigma_scale": info["sigma_scale"],
            "member_val_mse": info["member_val_mse"],
            "test_rows": [data.split.end_dev, len(data.clean)],
            "val_blocks": [list(b) for b in data.split.val_blocks],
            "onnx_max_diff": diff,
            **{k: v for k, v in asdict(report).items() if k != "pair"},
        }
    manifest: dict[str, Any] = {
        "variant": arch.variant,
        "n_steps": config.n_steps,
        "offset": config.offset,
        "constant": float(np.mean(np.concatenate(dev_errors))),
        "architecture": arch.to_dict(),
        "node_map": node_map,
        "training": {
            "csv": str(csv_path),
            "csv_sha256": file_sha256(csv_path),
            **{k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(config).items()},
            "torch": torch.__version__,
        },
        "mean_val_mse": float(np.mean([r.val_mse for r in reports])),
        "mean_val_mse_bias": float(np.mean([r.val_mse_bias for r in reports])),
        "pairs": entries,
    }
    write_manifest(out, manifest)
    return manifest, reports
