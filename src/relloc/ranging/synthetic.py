"""Synthetic ranging CSVs with a known, orientation-dependent UWB error (NumPy only).

For tests and for trying ``relloc ranging`` without the TIERS data: every robot turns at its
own rate while the pair distances oscillate, and each pair's error is

    error = bias + amplitude * cos(yaw_a - phase) + N(0, s^2),
    s = noise + noise_yaw * (1 + cos(yaw_a)) / 2

with ``yaw_a`` the heading of the robot carrying the pair's first node: a model that sees the
headings can learn it, a constant cannot; with ``noise_yaw`` the noise itself depends on the
heading (an uncertainty a model can learn). Ranges are quantised to 1 cm like the DWM1001's, and
rows come from a timer faster than the ranging, so rows repeat the previous range (as in the
real training CSV) and exercise the repeat removal.
"""

from __future__ import annotations

import csv
import itertools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from relloc.events import pair_key
from relloc.ranging.dataset import CSV_COLUMNS, DEFAULT_NODE_MAP


def synthetic_rows(
    robots: Sequence[str] = ("1", "3"),
    node_map: Mapping[str, str] | None = None,
    *,
    n_samples: int = 600,
    rate: float = 7.0,
    repeat_probability: float = 0.15,
    bias: float = 0.3,
    amplitude: float = 0.1,
    phase: float = 0.5,
    noise: float = 0.01,
    noise_yaw: float = 0.0,
    seed: int = 0,
) -> list[tuple[float, str, str, float, float, float, float, float]]:
    """Rows ``(timestamp, node1, node2, uwb_range, mocap_range, yaw1, yaw2, error)``.

    ``robots`` are the CSV's robot numbers; ``node_map`` (default: the loader's
    :data:`~relloc.ranging.dataset.DEFAULT_NODE_MAP`, else ``n_<number>``) maps them to node ids,
    which decides each pair's canonical first node: with the defaults, robots 1 and 3 give the
    pair ``n_3-n_7`` whose ``yaw_a`` is robot 3's heading.
    """
    rng = np.random.default_rng(seed)
    node_map = DEFAULT_NODE_MAP if node_map is None else node_map
    nodes = {r: node_map.get(r, f"n_{r}") for r in robots}
    turn_rate = {r: 0.25 + 0.2 * i for i, r in enumerate(robots)}
    rows = []
    last: dict[tuple[str, str], float] = {}
    t = 0.0
    for _ in range(n_samples):
        t += 1.0 / rate
        yaws = {r: math.remainder(turn_rate[r] * t + i, math.tau) for i, r in enumerate(robots)}
        for k, (r1, r2) in enumerate(itertools.combinations(robots, 2)):
            first = r1 if pair_key(nodes[r1], nodes[r2]).startswith(nodes[r1] + "-") else r2
            distance = 3.0 + k + math.sin(0.15 * t + k)
            if (r1, r2) in last and rng.random() < repeat_probability:
                measured = last[(r1, r2)]  # the timer read the same measurement again
            else:
                std = noise + noise_yaw * (1 + math.cos(yaws[first])) / 2
                error = bias + amplitude * math.cos(yaws[first] - phase) + rng.normal(0, std)
                measured = round(distance + error, 2)
            last[(r1, r2)] = measured
            rows.append((t, r1, r2, measured, distance, yaws[r1], yaws[r2], measured - distance))
    return rows


def write_synthetic_csv(path: str | Path, **kwargs: object) -> Path:
    """Write :func:`synthetic_rows` with the training CSV's header; returns the path."""
    path = Path(path)
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_COLUMNS)
        writer.writerows(synthetic_rows(**kwargs))  # type: ignore[arg-type]
    return path
