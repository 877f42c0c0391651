"""Score range-error models against honest baselines (NumPy and onnxruntime only).

The derivation: docs/explanation/internals.md, section ``relloc.ranging.evaluate``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from relloc.ranging.dataset import (
    DEFAULT_NODE_MAP,
    PairSeries,
    RangingDataError,
    drop_repeats,
    file_sha256,
    load_csv,
    make_windows,
)
from relloc.ranging.inference import ModelSet, PairModel
from relloc.ranging.manifest import find_model_dirs

PARTS = ("auto", "test", "all")
BASELINES = ("zero", "bias", "constant")

ONLINE_PRIOR_WEIGHT = 20.0
"""Weight, in samples, of the training constant in :func:`online_offset` (about 3 s of ranges)."""


def online_offset(
    values: np.ndarray, prior: float, weight: float = ONLINE_PRIOR_WEIGHT
) -> np.ndarray:
    """Causal running estimate of a session offset: before sample ``k``,
    ``(weight * prior + sum(values[:k])) / (weight + k)``.

    ``values`` are what the offset should explain (the true error minus the learned residual);
    the training constant is the prior, worth ``weight`` samples, so the estimate starts at the
    training constant and moves to the session's own mean as the session goes on.
    """
    seen = np.concatenate([[0.0], np.cumsum(values)[:-1]])
    k = np.arange(len(values), dtype=np.float64)
    return (weight * prior + seen) / (weight + k)


def support_guarded(
    model: PairModel, windows: np.ndarray, residual: np.ndarray, sigma: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """``(residual, sigma, n_out)`` as the run-time stage's support guard leaves them: a window
    outside the pair's training support (:mod:`relloc.ranging.support`) gets the pair's constant
    alone (residual 0, the constant's validation RMSE as sigma); no support recorded: unchanged."""
    if model.support is None:
        return residual, sigma, 0
    outside = ~model.support.contains(windows)
    constant_sigma = float(model.fallback_sigma) if model.fallback_sigma else sigma
    return (
        np.where(outside, 0.0, residual),
        np.where(outside, constant_sigma, sigma),
        int(np.count_nonzero(outside)),
    )


def _target_start(model_sets: Sequence[ModelSet], pair: str, clean: PairSeries, part: str) -> int:
    if part == "all":
        return 0
    starts = {tuple(ms.manifest["pairs"][pair].get("test_rows", ())) for ms in model_sets}
    if len(starts) != 1 or not next(iter(starts)):
        raise RangingDataError(
            f"pair {pair}: the model directories record different (or no) train/test splits; "
            "evaluate with --part all or on models trained together"
        )
    end_dev, n_rows = next(iter(starts))
    if n_rows != len(clean):
        raise RangingDataError(
            f"pair {pair}: the manifest split has {n_rows} rows but the CSV gives {len(clean)}; "
            "was it trained with another --node-map? Use --part all to score every row"
        )
    return int(end_dev)


def evaluate(
    csv_path: str | Path,
    model_dirs: Sequence[str | Path],
    *,
    part: str = "auto",
    node_map: Mapping[str, str] | None = None,
    timing_samples: int = 300,
    support_guard: bool = True,
) -> dict[str, Any]:
    """Evaluate the models under ``model_dirs`` (each a model directory or a parent of some).

    ``support_guard``: score the models as the run-time stage uses them (the default), with
    windows outside a pair's training support falling back to its constant
    (:func:`support_guarded`; counted in each model's ``out_of_support``); ``False`` scores the
    networks' own predictions everywhere.

    Returns a JSON-ready dict: ``{"csv", "part", "pairs", "skipped_pairs", "n_targets",
    "methods": {name: {"kind", "per_pair_mse", "mean_mse", "pooled_mse",
    "time_per_prediction_s", ...}}}``.
    """
    if part not in PARTS:
        raise ValueError(f"part must be one of {PARTS}, got {part!r}")
    dirs = find_model_dirs(list(model_dirs))
    model_sets = [ModelSet.load(d) for d in dirs]
    first = model_sets[0].manifest
    node_map = (
        dict(first.get("node_map") or DEFAULT_NODE_MAP) if node_map is None else dict(node_map)
    )
    sha = file_sha256(csv_path)
    if part == "auto":
        trained_on = {ms.manifest.get("training", {}).get("csv_sha256") for ms in model_sets}
        part = "test" if trained_on == {sha} else "all"
    series = load_csv(csv_path, node_map)
    covered = [p for p in series if all(p in ms for ms in model_sets)]
    skipped = {p: "no model in every directory" for p in series if p not in covered}
    if not covered:
        raise RangingDataError(
            f"{csv_path}: none of its pairs {sorted(series)} has a model in every directory"
        )
    n_max = max(ms.n_steps for ms in model_sets)
    names = _method_names(model_sets)
    online = [f"{n}+online" for n in ["bias", *names]]
    per_pair: dict[str, dict[str, float]] = {
        n: {} for n in ["zero", "bias", "constant", *names, *online]
    }
    sigma_z2: dict[str, list[np.ndarray]] = {n: [] for n in names}
    sigma_all: dict[str, list[np.ndarray]] = {n: [] for n in names}
    constant = float(first.get("constant", 0.0))
    sq_errors: dict[str, list[np.ndarray]] = {n: [] for n in per_pair}
    n_targets: dict[str, int] = {}
    timing_windows: list[tuple[str, np.ndarray]] = []
    out_of_support: dict[str, int] = {n: 0 for n in names}
    for pair in covered:
        clean, _ = drop_repeats(series[pair])
        start = max(_target_start(model_sets, pair, clean, part), n_max - 1)
        if start >= len(clean):
            skipped[pair] = "no rows to predict"
            continue
        targets = slice(start, len(clean))
        _, y, _ = make_windows(clean, n_max, targets)
        n_targets[pair] = len(y)
        bias = float(first["pairs"][pair].get("train_bias", 0.0))
        results = {
            "zero": y,
            "bias": y - bias,
            "constant": y - constant,
            "bias+online": y - online_offset(y, bias),
        }
        for name, ms in zip(names, model_sets, strict=True):
            w, y_m, _ = make_windows(clean, ms.n_steps, targets)
            assert np.array_equal(y_m, y)
            model = ms[pair]
            residual, sigma = model.predict_residual(w)
            if support_guard:
                residual, sigma, n_out = support_guarded(model, w, residual, sigma)
                out_of_support[name] += n_out
            results[name] = model.offset + residual - y
            results[f"{name}+online"] = online_offset(y - residual, model.offset) + residual - y
            sigma_z2[name].append((results[name] / sigma) ** 2)
            sigma_all[name].append(sigma)
            timing_windows.append((name, w[: max(1, timing_samples // len(covered))]))
        for name, err in results.items():
            per_pair[name][pair] = float(np.mean(err**2))
            sq_errors[name].append(err**2)
    if not n_targets:
        raise RangingDataError(f"{csv_path}: no pair has rows to predict in part {part!r}")
    timings = _time_predictions(model_sets, names, timing_windows)
    methods: dict[str, Any] = {}
    for name in per_pair:
        entry: dict[str, Any] = {
            "kind": "model" if name in names else ("baseline" if name in BASELINES else "online"),
            "per_pair_mse": per_pair[name],
            "mean_mse": float(np.mean(list(per_pair[name].values()))),
            "pooled_mse": float(np.mean(np.concatenate(sq_errors[name]))),
        }
        if name == "bias":
            entry["bias_per_pair"] = {
                p: float(first["pairs"][p].get("train_bias", 0.0)) for p in n_targets
            }
        if name == "constant":
            entry["constant"] = constant
        if name in timings:
            ms = model_sets[names.index(name)]
            z2 = np.concatenate(sigma_z2[name])
            entry.update(
                sigma_z_rms=float(np.sqrt(np.mean(z2))),
                sigma_cover_2=float(np.mean(z2 <= 4.0)),
                sigma_median=float(np.median(np.concatenate(sigma_all[name]))),
                fallback_pairs=sorted(p for p in n_targets if ms[p].fallback),
                variant=ms.variant,
                directory=str(ms.directory),
                n_steps=ms.n_steps,
                features=ms.manifest.get("architecture", {}).get("features"),
                time_per_prediction_s=timings[name],
            )
            if support_guard:
                entry["out_of_support"] = out_of_support[name]
        methods[name] = entry
    return {
        "csv": str(csv_path),
        "csv_sha256": sha,
        "part": part,
        "node_map": node_map,
        "pairs": sorted(n_targets),
        "skipped_pairs": skipped,
        "n_targets": n_targets,
        "methods": methods,
    }


def _method_names(model_sets: Sequence[ModelSet]) -> list[str]:
    """Variant names, made unique with the directory name where two share a variant."""
    variants = [ms.variant for ms in model_sets]
    names = []
    for ms in model_sets:
        name = ms.variant
        if variants.count(name) > 1 or name in BASELINES:
            name = f"{ms.variant}:{ms.directory.name}"
        names.append(name)
    return names


def _time_predictions(
    model_sets: Sequence[ModelSet], names: Sequence[str], windows: Sequence[tuple[str, np.ndarray]]
) -> dict[str, dict[str, float]]:
    """Median/mean/p90 seconds of one single-window prediction, per method."""
    out: dict[str, dict[str, float]] = {}
    for name, ms in zip(names, model_sets, strict=True):
        samples = [w for n, w in windows if n == name]
        if not samples:
            continue
        model = next(iter(ms.values()))  # every pair's model has the same architecture
        stacked = np.concatenate(samples).astype(np.float32)
        model.predict_raw(stacked[:1])  # warm-up: first run allocates
        times = []
        for i in range(len(stacked)):
            t0 = time.perf_counter()
            model.predict_raw(stacked[i : i + 1])
            times.append(time.perf_counter() - t0)
        out[name] = {
            "median": float(np.median(times)),
            "mean": float(np.mean(times)),
            "p90": float(np.percentile(times, 90)),
            "n": len(times),
        }
    return out
