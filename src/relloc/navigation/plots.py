"""The navigation figure: planned path, estimate and true trajectory; errors over time."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from relloc.navigation.closed_loop import NavResult

__all__ = ["plot_navigation"]


def plot_navigation(result: NavResult, path: Path) -> Path:
    """Two panels, written as a PNG.

    Left: in the relative frame (the reference robot at the origin), the planned path, the
    robot's true trajectory and the estimates it navigated on, with the start and the stops.
    Right: positioning APE of each estimate and tracking error of the true position over time,
    with the moment the safety gate released the robot and the moment it reached the path.
    """
    s = result.summary()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12.5, 5.2), gridspec_kw={"width_ratios": [1, 1.2]})
    pts = result.path.points
    ax.plot(pts[:, 0], pts[:, 1], "k--", lw=1.5, label="planned path")
    ax.plot(pts[0, 0], pts[0, 1], "ks", ms=7, mfc="none")
    drive = (result.gt_t >= result.start_time) & (result.gt_t <= result.end_time)
    if not math.isfinite(result.start_time):
        drive[:] = False
    ax.plot(
        result.gt_xy[drive, 0],
        result.gt_xy[drive, 1],
        "-",
        color="C0",
        lw=2.2,
        alpha=0.8,
        label="true trajectory",
    )
    keep = (result.estimate_t >= result.start_time) & (result.estimate_t <= result.end_time)
    ax.plot(
        result.estimate_xy[keep, 0],
        result.estimate_xy[keep, 1],
        ".",
        color="C3",
        ms=2.5,
        label="PF estimate (feedback)",
    )
    if result.gt_xy.size:
        ax.plot(result.gt_xy[0, 0], result.gt_xy[0, 1], "o", color="C0", ms=7, label="start")
    ax.plot([0], [0], "k*", ms=13, label=f"reference {result.reference}")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"x relative to {result.reference} (m)")
    ax.set_ylabel(f"y relative to {result.reference} (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    done = "completed" if result.completed else "NOT completed"
    ax.set_title(f"nav: {result.robot} on the relative estimate ({done})")

    if result.estimate_t.size:
        ape = np.linalg.norm(result.estimate_xy - result.estimate_truth, axis=1)
        ax2.plot(result.estimate_t, ape, lw=1, color="C3", label="positioning APE (estimate)")
    trk_t = result.gt_t[result.tracking_window()]
    if trk_t.size:
        ax2.plot(
            trk_t,
            result.tracking_errors(),
            lw=1.2,
            color="C0",
            label="tracking error (truth to path)",
        )
    for t, label, style in (
        (result.start_time, "gate released", "g--"),
        (result.path_start_time, "path reached", "b:"),
        (result.end_time, "end", "k--"),
    ):
        if math.isfinite(t):
            ax2.axvline(t, color=style[0], ls=style[1:], lw=1, label=label)
    # Linear scale, sized to the errors while driving (the APE before convergence, metres
    # from the uniform prior, runs off the top: the gate held the robot then).
    driving = (result.estimate_t >= result.start_time) & (result.estimate_t <= result.end_time)
    tops = [0.1]
    if driving.any():
        tops.append(
            float(
                np.max(
                    np.linalg.norm(
                        result.estimate_xy[driving] - result.estimate_truth[driving], axis=1
                    )
                )
            )
        )
    if trk_t.size:
        tops.append(float(np.max(result.tracking_errors())))
    ax2.set_ylim(0.0, 1.3 * max(tops))
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("error (m)")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8, loc="upper right")

    def fmt(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.3f}"

    ax2.set_title(
        f"APE median {fmt(s['ape_median'])} m (std {fmt(s['ape_std'])}), "
        f"tracking median {fmt(s['tracking_median'])} m (std {fmt(s['tracking_std'])})",
        fontsize=10,
    )
    fig.suptitle(
        f"seed {result.seed}, {result.particles} particles, control at {result.rate_hz:g} Hz"
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
