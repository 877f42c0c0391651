"""UWB range-error data: CSV loading and validation, repeat removal, block splits, windows.

NumPy only (no torch): the evaluation and the run-time stage use it too.

The training CSV (``train_20221219.csv``) has one row per pair and timer tick::

    timestamp,node1,node2,uwb_range,mocap_range,tb_node1_yaw,tb_node2_yaw,error

with ``error = uwb_range - mocap_range`` (m) and the yaws (rad) of the robots carrying the two
nodes, from motion capture. ``node1``/``node2`` are *robot numbers*; ranging errors belong to the
transceivers, so :data:`DEFAULT_NODE_MAP` turns them into UWB node ids and every series is keyed
by :func:`relloc.events.pair_key` of the nodes (``"n_3-n_7"``).

The derivation: docs/explanation/internals.md, section ``relloc.ranging.dataset``.
"""

from __future__ import annotations

import csv
import hashlib
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relloc.events import pair_key

CSV_COLUMNS: tuple[str, ...] = (
    "timestamp",
    "node1",
    "node2",
    "uwb_range",
    "mocap_range",
    "tb_node1_yaw",
    "tb_node2_yaw",
    "error",
)
"""The TIERS UWB-error table layout (``error = uwb_range - mocap_range``); written by
``relloc ranging bag-csv`` and the synthetic generator, read by training and calibration."""

REQUIRED_COLUMNS: tuple[str, ...] = (
    "timestamp",
    "node1",
    "node2",
    "uwb_range",
    "tb_node1_yaw",
    "tb_node2_yaw",
)
"""Columns a ranging CSV must have; it also needs ``error`` or ``mocap_range`` (or both)."""

DEFAULT_NODE_MAP: dict[str, str] = {"1": "n_7", "3": "n_3", "4": "n_4", "5": "n_5"}
"""Robot number in the training CSV -> UWB node it carried (see the data README)."""

DEFAULT_SPLIT: tuple[float, float, float] = (0.7, 0.1, 0.2)
"""Fractions of each pair's (repeat-free) rows: train, validation (in blocks), test (last)."""

DEFAULT_VAL_BLOCKS = 3
"""Validation blocks spread over the rows before the test part (see :func:`block_split`)."""


class RangingDataError(ValueError):
    """A ranging CSV (or a node map) cannot be used; the message says which file, line, column."""


@dataclass(frozen=True)
class PairSeries:
    """Chronological samples of one UWB node pair, in canonical node order.

    ``yaw_a`` is the heading of the robot carrying ``node_a`` (the node that sorts first),
    ``yaw_b`` that of ``node_b``. ``error`` is ``range - true distance`` (m).
    """

    pair: str
    node_a: str
    node_b: str
    t: np.ndarray
    range: np.ndarray
    yaw_a: np.ndarray
    yaw_b: np.ndarray
    error: np.ndarray

    def __len__(self) -> int:
        return len(self.range)

    def take(self, index: np.ndarray | slice) -> PairSeries:
        """The samples selected by ``index`` (a slice or an index/boolean array)."""
        return PairSeries(
            self.pair,
            self.node_a,
            self.node_b,
            self.t[index],
            self.range[index],
            self.yaw_a[index],
            self.yaw_b[index],
            self.error[index],
        )

    def frames(self) -> np.ndarray:
        """``(n, 3)`` array of ``[range, yaw_a, yaw_b]``: what a model sees of each sample."""
        return np.column_stack([self.range, self.yaw_a, self.yaw_b])


# ---------------------------------------------------------------------------- node map
def parse_node_map(text: str) -> dict[str, str]:
    """Parse ``"1=n_7,3=n_3"`` into ``{"1": "n_7", "3": "n_3"}``.

    Raises :class:`RangingDataError` on a malformed item or a node given to two robots.
    """
    mapping: dict[str, str] = {}
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        key, sep, node = (s.strip() for s in item.partition("="))
        if not sep or not key or not node:
            raise RangingDataError(f"node map item {item!r} must look like '1=n_7'")
        mapping[_robot_number(key)] = node
    if not mapping:
        raise RangingDataError(f"node map {text!r} names no robot")
    nodes = list(mapping.values())
    if len(set(nodes)) != len(nodes):
        raise RangingDataError(f"node map {text!r} gives one node to two robots")
    return mapping


def format_node_map(mapping: Mapping[str, str]) -> str:
    """Inverse of :func:`parse_node_map`."""
    return ",".join(f"{k}={v}" for k, v in mapping.items())


def _robot_number(text: str) -> str:
    """``"1.0"`` and ``"1"`` both name robot ``"1"`` (the CSV writes robot numbers as floats)."""
    text = text.strip()
    try:
        value = float(text)
    except ValueError:
        return text
    if math.isfinite(value) and value == int(value):
        return str(int(value))
    return text


def _node_of(value: str, node_map: Mapping[str, str], where: str) -> str:
    key = _robot_number(value)
    if key in node_map:
        return node_map[key]
    if key.startswith("n_"):
        return key  # already a node id
    raise RangingDataError(
        f"{where}: robot {value!r} is not in the node map {format_node_map(node_map)!r}; "
        "pass --node-map with every robot of the file (e.g. 1=n_7,3=n_3)"
    )


# ---------------------------------------------------------------------------- loading
def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file: lets evaluation recognise the CSV a model was trained on."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def load_csv(path: str | Path, node_map: Mapping[str, str] | None = None) -> dict[str, PairSeries]:
    """Read a ranging CSV into one chronological :class:`PairSeries` per node pair.

    Rows keep file order within a pair (stable sort by timestamp). Raises
    :class:`RangingDataError` if the file is missing or empty, lacks a column, or has a value
    that is not a finite number; the message names the line and the column.
    """
    node_map = DEFAULT_NODE_MAP if node_map is None else node_map
    path = Path(path)
    try:
        fh = path.open(newline="")
    except FileNotFoundError:
        raise RangingDataError(f"ranging CSV not found: {path}") from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise RangingDataError(f"{path}: the file is empty") from None
        missing = [c for c in REQUIRED_COLUMNS if c not in header]
        if "error" not in header and "mocap_range" not in header:
            missing.append("error (or mocap_range)")
        if missing:
            raise RangingDataError(
                f"{path}: missing column(s) {missing}; a ranging CSV needs "
                f"{[*REQUIRED_COLUMNS, 'error']} (error = uwb_range - mocap_range)"
            )
        col = {name: i for i, name in enumerate(header)}
        numeric = [c for c in ("timestamp", "uwb_range", "tb_node1_yaw", "tb_node2_yaw")]
        numeric += [c for c in ("error", "mocap_range") if c in col]
        rows: dict[str, list[tuple[float, float, float, float, float]]] = {}
        nodes_of_pair: dict[str, tuple[str, str]] = {}
        for line_no, row in enumerate(reader, start=2):
            if not row or all(not cell.strip() for cell in row):
                continue
            where = f"{path}:{line_no}"
            if len(row) != len(header):
                raise RangingDataError(f"{where}: {len(row)} fields, the header has {len(header)}")
            values: dict[str, float] = {}
            for name in numeric:
                cell = row[col[name]].strip()
                try:
                    value = float(cell)
                except ValueError:
                    raise RangingDataError(
                        f"{where}: column {name!r} is {cell!r}, not a number"
                    ) from None
                if not math.isfinite(value):
                    raise RangingDataError(f"{where}: column {name!r} is {cell!r} (not finite)")
                values[name] = value
            node1 = _node_of(row[col["node1"]], node_map, where)
            node2 = _node_of(row[col["node2"]], node_map, where)
            if node1 == node2:
                raise RangingDataError(f"{where}: node1 and node2 are both {node1}")
            error = (
                values["error"]
                if "error" in values
                else values["uwb_range"] - values["mocap_range"]
            )
            yaw1, yaw2 = values["tb_node1_yaw"], values["tb_node2_yaw"]
            key = pair_key(node1, node2)
            yaw_a, yaw_b = (yaw1, yaw2) if node1 < node2 else (yaw2, yaw1)
            rows.setdefault(key, []).append(
                (values["timestamp"], values["uwb_range"], yaw_a, yaw_b, error)
            )
            nodes_of_pair[key] = tuple(sorted((node1, node2)))  # type: ignore[assignment]
    if not rows:
        raise RangingDataError(f"{path}: no data rows")
    series: dict[str, PairSeries] = {}
    for key in sorted(rows):
        arr = np.asarray(rows[key], dtype=np.float64)
        arr = arr[np.argsort(arr[:, 0], kind="stable")]
        node_a, node_b = nodes_of_pair[key]
        series[key] = PairSeries(
            key, node_a, node_b, arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4]
        )
    return series


def drop_repeats(series: PairSeries) -> tuple[PairSeries, int]:
    """Keep only samples whose range differs from the pair's previous sample.

    Returns the reduced series and how many samples were dropped. A repeated range is the same
    UWB measurement read again by a faster timer, not a new observation.
    """
    if len(series) == 0:
        return series, 0
    keep = np.ones(len(series), dtype=bool)
    keep[1:] = series.range[1:] != series.range[:-1]
    return series.take(keep), int((~keep).sum())


# ---------------------------------------------------------------------------- splits, windows
def split_bounds(n: int, fractions: Iterable[float] = DEFAULT_SPLIT) -> tuple[int, int]:
    """Row indices ``(end_train, end_dev)``: the fractions' bounds; rows ``end_dev:`` are the test part."""
    fr = [float(f) for f in fractions]
    if len(fr) != 3 or any(f < 0 for f in fr) or not math.isclose(sum(fr), 1.0, abs_tol=1e-6):
        raise ValueError(f"split must be three non-negative fractions summing to 1, got {fr}")
    end_train = round(n * fr[0])
    end_val = round(n * (fr[0] + fr[1]))
    return end_train, end_val


@dataclass(frozen=True)
class BlockSplit:
    """Which rows of a pair's repeat-free series train, validate and test a model."""

    train: np.ndarray
    """Indices of the training target rows."""
    val: np.ndarray
    """Indices of the validation target rows (``val_blocks`` blocks, far apart)."""
    val_blocks: tuple[tuple[int, int], ...]
    """``(start, stop)`` of each validation block."""
    end_dev: int
    """First test row: rows ``end_dev:`` are the held-out test part."""
    n: int


def block_split(
    n: int,
    fractions: Iterable[float] = DEFAULT_SPLIT,
    val_blocks: int = DEFAULT_VAL_BLOCKS,
    gap: int = 0,
) -> BlockSplit:
    """Test part last; validation in ``val_blocks`` blocks spread over the rows before it.

    The rows before the test part (``0:end_dev``, from :func:`split_bounds`) are cut into
    ``val_blocks`` equal stretches; the middle of each holds one validation block, so the
    blocks are as far apart as the data allows and together hold the validation fraction.
    Training rows are the others, except ``gap`` rows on each side of every block and before
    the test part: a training target right next to a held-out one is nearly a copy of it.
    """
    if val_blocks < 1 or gap < 0:
        raise ValueError(f"val_blocks must be >= 1 and gap >= 0, got {val_blocks}, {gap}")
    end_train, end_dev = split_bounds(n, fractions)
    n_val = end_dev - end_train
    length = max(1, n_val // val_blocks) if n_val > 0 else 0
    blocks = []
    for k in range(val_blocks if length else 0):
        centre = (2 * k + 1) * end_dev / (2 * val_blocks)
        start = max(0, min(end_dev - length, round(centre - length / 2)))
        blocks.append((start, start + length))
    is_val = np.zeros(n, dtype=bool)
    excluded = np.zeros(n, dtype=bool)
    excluded[max(0, end_dev - gap) :] = True
    for start, stop in blocks:
        is_val[start:stop] = True
        excluded[max(0, start - gap) : stop + gap] = True
    train = np.flatnonzero(~excluded & (np.arange(n) < end_dev))
    return BlockSplit(train, np.flatnonzero(is_val), tuple(blocks), end_dev, n)


def make_windows(
    series: PairSeries, n_steps: int, targets: slice | np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sliding windows of the last ``n_steps`` frames and the error at each window's last frame.

    ``targets`` selects which samples to predict (a slice or an array of indices; default: all
    that have a full history); a
    window may reach back before ``targets.start`` (its inputs are ranges and yaws only, never
    errors, so nothing of a held-out target leaks). Returns ``(windows (N, n_steps, 3),
    errors (N,), index (N,))`` where ``index`` is each target's position in ``series``.
    """
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    n = len(series)
    if isinstance(targets, np.ndarray):
        index = np.asarray(targets, dtype=np.int64)
        index = index[(index >= n_steps - 1) & (index < n)]
    else:
        start, stop = 0, n
        if targets is not None:
            start, stop, _ = targets.indices(n)
        index = np.arange(max(start, n_steps - 1), stop)
    if len(index) == 0:
        return (
            np.zeros((0, n_steps, 3)),
            np.zeros(0),
            np.zeros(0, dtype=np.int64),
        )
    frames = series.frames()
    gather = index[:, None] + np.arange(-n_steps + 1, 1)[None, :]
    return frames[gather], series.error[index], index
