"""How long a bag's range stamps lag the geometry they measure, from motion capture.

A UWB driver that averages its ranges (a LinkTrack set to average over a second) stamps each
one at the end of its window: the distance it reports is the bodies' distance half a window
earlier. While the robots move that lag is an error of their speed times the lag, which no bias
explains. :func:`range_delay` finds it as the lag that best lines the ranges up with the
mocap distances between the bodies carrying the tags (each pair's own constant removed: a
bias and the lever arms, which the lag does not change), and says it only where the ranges
say so clearly: a team that barely moves leaves it at 0.

The 3D smoother reads it (``uwb.range_delay``); ``relloc init`` writes it for a flying team.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from relloc.drafting.tags import Poses, pose_at
from relloc.events import pair_key
from relloc.sources.inspect_bag import BagInventory

MAX_DELAY_S = 1.5
"""Longest lag searched (s): a 2 s averaging window and some latency."""
DELAY_STEP_S = 0.05
"""Resolution of the search (s)."""
CLEAR_GAIN = 0.8
"""The lag is said only where it brings the ranges' spread about the mocap distances below
this fraction of the spread at no lag."""


def delay_spread(
    inv: BagInventory, poses: Poses, node_body: Mapping[str, str], dim: int, lag: float
) -> float:
    """Median absolute deviation (m) of the ranges between the nodes of ``node_body`` (node ->
    mocap body) about the bodies' mocap distance ``lag`` seconds before each stamp, each
    pair's median removed; NaN where no pair has samples."""
    nodes = sorted(node_body)
    deviations: list[np.ndarray] = []
    for i, a in enumerate(nodes):
        for b in nodes[i + 1 :]:
            if node_body[a] == node_body[b]:
                continue
            r = inv.ranges.get(pair_key(a, b))
            if r is None or r.shape[0] < 10:
                continue
            t = r[:, 0] - lag
            pa, _, oka = pose_at(poses[node_body[a]], t, dim)
            pb, _, okb = pose_at(poses[node_body[b]], t, dim)
            ok = oka & okb & np.isfinite(r[:, 1])
            if ok.sum() < 10:
                continue
            res = r[ok, 1] - np.linalg.norm(pa[ok] - pb[ok], axis=1)
            deviations.append(np.abs(res - np.median(res)))
    return float(np.median(np.concatenate(deviations))) if deviations else float("nan")


def range_delay(
    inv: BagInventory, poses: Poses, node_body: Mapping[str, str], dim: int
) -> tuple[float, float, float]:
    """``(delay, spread at it, spread at 0)``: the lag (s, a multiple of ``DELAY_STEP_S`` up to
    ``MAX_DELAY_S``) with the least :func:`delay_spread`, or 0 where it does not bring the
    spread below ``CLEAR_GAIN`` of the spread at no lag."""
    lags = np.arange(0.0, MAX_DELAY_S + 1e-9, DELAY_STEP_S)
    spreads = np.array([delay_spread(inv, poses, node_body, dim, float(g)) for g in lags])
    if not np.isfinite(spreads).any():
        return 0.0, float("nan"), float("nan")
    best = int(np.nanargmin(spreads))
    at_zero = float(spreads[0])
    if not spreads[best] < CLEAR_GAIN * at_zero:
        return 0.0, at_zero, at_zero
    return round(float(lags[best]), 3), float(spreads[best]), at_zero


def shifted(inv: BagInventory, delay: float) -> BagInventory:
    """``inv`` with every range stamped ``delay`` seconds earlier: at the geometry it measured."""
    if delay == 0.0:
        return inv
    ranges = {k: np.column_stack([v[:, 0] - delay, v[:, 1]]) for k, v in inv.ranges.items()}
    return replace(inv, ranges=ranges)
