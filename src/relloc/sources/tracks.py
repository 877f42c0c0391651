"""A sampled 2-D track (motion capture) read at other times, refusing the gaps where the body
was lost: what calibration and bag inspection compare ranges with."""

from __future__ import annotations

import numpy as np

__all__ = ["interpolate_track"]


def interpolate_track(
    times: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    t: np.ndarray,
    *,
    max_gap: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation of a sorted 2-D track at times ``t``, refusing long gaps.

    Returns ``(x, y, valid)``; ``valid`` is false outside the track and where the two samples
    around ``t`` are more than ``max_gap`` seconds apart (the mocap lost the body).
    """
    times = np.asarray(times, dtype=float)
    t = np.asarray(t, dtype=float)
    if times.size == 0:
        nan = np.full(t.shape, np.nan)
        return nan, nan.copy(), np.zeros(t.shape, dtype=bool)
    hi = np.clip(np.searchsorted(times, t, side="left"), 0, times.size - 1)
    lo = np.clip(hi - 1, 0, times.size - 1)
    exact = times[hi] == t
    gap = times[hi] - times[lo]
    inside = (t >= times[0]) & (t <= times[-1])
    valid = inside & (exact | (gap <= max_gap))
    x = np.interp(t, times, xs)
    y = np.interp(t, times, ys)
    return x, y, valid
