"""``relloc ranging``: train, evaluate and export the learned UWB range-error models.

::

    relloc ranging train CSV --variant stacked|bilstm|convlstm --out DIR [--json FILE]
    relloc ranging eval CSV --models DIR [DIR ...] [--json FILE]
    relloc ranging export DIR                 # re-export ONNX from the torch checkpoints
    relloc ranging bag-csv BAG --bodies n_7=turtlebot1_cap,n_3=turtlebot3_cap --out CSV

``train`` and ``export`` need the optional extra ``relloc[train]`` (torch); it is imported only
when they run, so ``eval`` and the rest of relloc work without it. Also runnable on its own as
``python -m relloc.cli.ranging ...``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from relloc.cli import argtypes
from relloc.cli.common import UserError, options_from_args
from relloc.ranging.dataset import (
    DEFAULT_NODE_MAP,
    DEFAULT_SPLIT,
    DEFAULT_VAL_BLOCKS,
    RangingDataError,
    format_node_map,
    parse_node_map,
)
from relloc.ranging.manifest import ModelDirError

VARIANT_CHOICES = ("stacked", "bilstm", "convlstm")
FEATURE_CHOICES = ("relative", "invariant", "paper")


def _ints(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from None
    if not values:
        raise argparse.ArgumentTypeError("expected at least one integer")
    return values


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None


def _node_map(text: str) -> dict[str, str]:
    try:
        return parse_node_map(text)
    except RangingDataError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _write_json(path: str | None, data: Any) -> None:
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(data, indent=2) + "\n")


def _stdout() -> Console:
    """Console for tables: wide enough for one row per pair when output is not a terminal."""
    return Console() if sys.stdout.isatty() else Console(width=160)


# ---------------------------------------------------------------------------- train
def _train(args: argparse.Namespace) -> int:
    try:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

        from relloc.ranging.models import Architecture
        from relloc.ranging.train import TrainConfig, train_directory
    except ImportError as exc:
        raise UserError(f"training needs the optional extra relloc[train] (torch): {exc}") from None
    console = _stdout()
    try:
        arch = options_from_args(Architecture, args)
        config = options_from_args(TrainConfig, args, split=tuple(args.split))
    except ValueError as exc:
        raise UserError(str(exc)) from None
    pairs = [p.strip() for p in args.pairs.split(",")] if args.pairs else None
    progress = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("val MSE {task.fields[mse]:.5f} m²"),
        console=console,
        disable=args.no_progress,
    )
    tasks: dict[str, Any] = {}

    def on_epoch(pair: str, epoch: int, max_epochs: int, mse: float) -> None:
        if pair not in tasks:
            tasks[pair] = progress.add_task(f"{args.variant} {pair}", total=max_epochs, mse=mse)
        progress.update(tasks[pair], completed=epoch, mse=mse)

    try:
        with progress:
            manifest, reports = train_directory(
                args.csv,
                args.out,
                arch,
                config,
                node_map=args.node_map,
                pairs=pairs,
                progress=on_epoch,
            )
    except (RangingDataError, ValueError) as exc:
        raise UserError(str(exc)) from None
    table = Table(title=f"{args.variant}: training report ({args.out})")
    for col in (
        "pair",
        "rows",
        "repeats",
        "train",
        "val",
        "test",
        "epochs (best)",
        "val MSE",
        "val MSE bias",
        "fallback",
        "time s",
    ):
        table.add_column(col, justify="right")
    for r in reports:
        table.add_row(
            r.pair,
            str(r.n_rows),
            str(r.repeats_dropped),
            str(r.n_train),
            str(r.n_val),
            str(r.n_test),
            f"{r.epochs} ({','.join(map(str, r.best_epoch))})",
            f"{r.val_mse:.5f}",
            f"{r.val_mse_bias:.5f}",
            "yes" if r.fallback else "",
            f"{r.train_time_s:.1f}",
        )
    table.add_row(
        "mean",
        *[""] * 6,
        f"{manifest['mean_val_mse']:.5f}",
        f"{manifest['mean_val_mse_bias']:.5f}",
        "",
        "",
    )
    console.print(table)
    _write_json(args.json, manifest)
    return 0


# ---------------------------------------------------------------------------- eval
def _eval(args: argparse.Namespace) -> int:
    from relloc.ranging.evaluate import evaluate

    try:
        report = evaluate(
            args.csv,
            args.models,
            part=args.part,
            node_map=args.node_map,
            timing_samples=args.timing_samples,
            support_guard=not args.no_support_guard,
        )
    except (RangingDataError, ModelDirError) as exc:
        raise UserError(str(exc)) from None
    pairs = report["pairs"]
    table = Table(
        title=f"MSE of the predicted ranging error (m²), part={report['part']}: {args.csv}"
    )
    table.add_column("method")
    table.add_column("mean", justify="right")
    table.add_column("pooled", justify="right")
    for p in pairs:
        table.add_column(p, justify="right")
    table.add_column("ms/pred", justify="right")
    table.add_column("σ z-rms", justify="right")
    table.add_column("fallback", justify="left")
    guarded = any("out_of_support" in m for m in report["methods"].values())
    if guarded:
        table.add_column("outside support", justify="right")
    for name, m in report["methods"].items():
        timing = m.get("time_per_prediction_s")
        table.add_row(
            name,
            f"{m['mean_mse']:.5f}",
            f"{m['pooled_mse']:.5f}",
            *[f"{m['per_pair_mse'][p]:.5f}" for p in pairs],
            f"{timing['median'] * 1e3:.3f}" if timing else "-",
            f"{m['sigma_z_rms']:.2f}" if "sigma_z_rms" in m else "-",
            ",".join(m.get("fallback_pairs", [])) or "-",
            *([str(m["out_of_support"]) if "out_of_support" in m else "-"] if guarded else []),
        )
    _stdout().print(table)
    if report["skipped_pairs"]:
        _stdout().print(f"skipped pairs: {report['skipped_pairs']}")
    _write_json(args.json, report)
    return 0


# ---------------------------------------------------------------------------- export
def _export(args: argparse.Namespace) -> int:
    try:
        from relloc.ranging.export import reexport_dir
    except ImportError as exc:
        raise UserError(f"export needs the optional extra relloc[train] (torch): {exc}") from None
    try:
        diffs = reexport_dir(args.dir, tolerance=args.tolerance)
    except (ModelDirError, FileNotFoundError, RuntimeError) as exc:
        raise UserError(str(exc)) from None
    for pair, diff in diffs.items():
        Console().print(f"{pair}: exported, max |onnx - torch| = {diff:.2e} m")
    return 0


# ---------------------------------------------------------------------------- bag-csv
def _bag_csv(args: argparse.Namespace) -> int:
    from relloc.evaluation.range_errors import bag_rows, parse_bodies, write_csv

    try:
        rows = bag_rows(args.bag, parse_bodies(args.bodies), args.mocap_topic)
    except RangingDataError as exc:
        raise UserError(str(exc)) from None
    write_csv(rows, args.out)
    Console().print(f"{len(rows)} rows -> {args.out}")
    return 0


# ---------------------------------------------------------------------------- wiring
def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``ranging`` with its ``train``, ``eval``, ``export`` and ``bag-csv`` subcommands."""
    ranging = subparsers.add_parser(
        "ranging",
        help="learned UWB range-error correction: train, eval, export",
        description="Train, evaluate and export per-node-pair UWB range-error models.",
    )
    sub = ranging.add_subparsers(dest="ranging_command", required=True)
    node_map_help = (
        "CSV robot number -> UWB node, e.g. 1=n_7,3=n_3 "
        f"(default for train: {format_node_map(DEFAULT_NODE_MAP)})"
    )

    train = sub.add_parser(
        "train",
        help="train one model per node pair from a ranging CSV",
        description="Train one range-error model per UWB node pair from a ranging CSV (needs the train extra: torch) and write a model directory with ONNX files and a manifest.",
    )
    train.add_argument("csv", help="ranging CSV (columns of train_20221219.csv)")
    train.add_argument(
        "--variant",
        choices=VARIANT_CHOICES,
        default="stacked",
        help="network: stacked LSTM, bidirectional LSTM or ConvLSTM (docs/explanation/range-correction.md)",
    )
    train.add_argument("--out", required=True, help="model directory to write")
    train.add_argument("--n-steps", type=int, default=10, help="frames per window (default 10)")
    train.add_argument(
        "--hidden",
        type=_ints,
        default=(50, 50),
        help="units (filters) per recurrent layer (default 50,50)",
    )
    train.add_argument(
        "--dropout", type=float, default=0.3, help="dropout between recurrent layers"
    )
    train.add_argument(
        "--features",
        choices=FEATURE_CHOICES,
        default="relative",
        help="input features (default relative; see docs/explanation/range-correction.md)",
    )
    train.add_argument(
        "--conv-subseq",
        type=int,
        default=5,
        help="convlstm: frames per sub-sequence (divides --n-steps)",
    )
    train.add_argument("--conv-kernel", type=int, default=3, help="convlstm: kernel size")
    train.add_argument("--epochs", type=int, default=150, help="maximum epochs")
    train.add_argument("--patience", type=int, default=15, help="early-stopping patience")
    train.add_argument("--batch-size", type=int, default=32, help="windows per training batch")
    train.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate")
    train.add_argument("--weight-decay", type=float, default=1e-4, help="L2 weight decay")
    train.add_argument(
        "--seed", type=argtypes.seed, default=0, help="random seed of the weights and batches"
    )
    train.add_argument(
        "--split",
        type=_floats,
        default=DEFAULT_SPLIT,
        help="train,val,test fractions (default 0.7,0.1,0.2); test = the last rows",
    )
    train.add_argument(
        "--val-blocks",
        type=int,
        default=DEFAULT_VAL_BLOCKS,
        help=f"validation blocks spread over the rows before the test part "
        f"(default {DEFAULT_VAL_BLOCKS})",
    )
    train.add_argument(
        "--ensemble",
        type=int,
        default=1,
        help="models per pair from different seeds; their spread adds to the sigma (default 1)",
    )
    train.add_argument(
        "--val-gap",
        type=int,
        default=None,
        help="rows left out of training around each validation block and before the test "
        "part (default: --n-steps)",
    )
    train.add_argument(
        "--guard-margin",
        type=float,
        default=0.1,
        help="fall back to the pair's constant unless the model beats its validation MSE "
        "by this fraction (default 0.1)",
    )
    train.add_argument(
        "--offset",
        choices=("manifest", "filter"),
        default="manifest",
        help="run time: add the pair's constant (manifest) or leave it to the filter's pair "
        "bias (filter); default manifest",
    )
    train.add_argument(
        "--node-map", type=_node_map, default=dict(DEFAULT_NODE_MAP), help=node_map_help
    )
    train.add_argument("--pairs", help="train only these pairs, e.g. n_3-n_7,n_4-n_5")
    train.add_argument("--json", help="also write the training report (the manifest) here")
    train.add_argument("--no-progress", action="store_true", help="no progress bar")
    train.set_defaults(handler=_train)

    ev = sub.add_parser(
        "eval",
        help="score models and the zero/bias baselines on a CSV",
        description="Score trained model directories (onnxruntime) and the zero and constant-bias baselines on a ranging CSV: MSE of the predicted ranging error per pair.",
    )
    ev.add_argument("csv", help="ranging CSV (any file with the training CSV's columns)")
    ev.add_argument(
        "--models",
        nargs="+",
        required=True,
        help="model directories, or parents of several (one per variant)",
    )
    ev.add_argument("--json", help="write the full report here")
    ev.add_argument(
        "--part",
        choices=("auto", "test", "all"),
        default="auto",
        help="rows to score: auto = the held-out test part if the CSV is the "
        "training CSV, else all rows",
    )
    ev.add_argument(
        "--node-map",
        type=_node_map,
        default=None,
        help="CSV robot number -> UWB node (default: the models' training map)",
    )
    ev.add_argument(
        "--timing-samples",
        type=int,
        default=300,
        help="single-window predictions timed per variant",
    )
    ev.add_argument(
        "--no-support-guard",
        action="store_true",
        help="score the networks' predictions on every window; by default a window outside "
        "its pair's training support gets the pair's constant, as at run time",
    )
    ev.set_defaults(handler=_eval)

    ex = sub.add_parser(
        "export",
        help="re-export a model directory's ONNX files from torch",
        description="Re-export the ONNX files of a model directory from its torch checkpoints and check them against torch (needs the train extra).",
    )
    ex.add_argument("dir", help="model directory written by `relloc ranging train`")
    ex.add_argument(
        "--tolerance", type=float, default=1e-5, help="largest accepted |onnx - torch| (m)"
    )
    ex.set_defaults(handler=_export)

    bag = sub.add_parser(
        "bag-csv",
        help="ranging CSV from a rosbag2 recording with mocap",
        description="Write a ranging CSV (the training CSV's columns) from a rosbag2 recording with UWB ranges and motion capture.",
    )
    bag.add_argument("bag", help="rosbag2 directory")
    bag.add_argument(
        "--bodies",
        required=True,
        help="UWB node -> motion-capture body, e.g. n_7=turtlebot1_cap,n_3=turtlebot3_cap",
    )
    bag.add_argument("--out", required=True, help="CSV to write")
    bag.add_argument(
        "--mocap-topic",
        default="/vrpn_client_node/{body}/pose",
        help="motion-capture topic template",
    )
    bag.set_defaults(handler=_bag_csv)


def main(argv: Sequence[str] | None = None) -> int:
    """Stand-alone entry point: ``python -m relloc.cli.ranging ranging train ...``, the same as
    ``relloc ranging train ...`` (same parser, same one-line errors)."""
    from relloc.cli import main as relloc_main

    return relloc_main(argv)


if __name__ == "__main__":
    sys.exit(main())
