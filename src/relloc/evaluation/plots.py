"""Plots people in this field recognise, written as PNG files: relative trajectories over the
truth, APE distributions per robot and method (box plots), APE over time.

Every plot names the reference robot (positions are relative to it) and what the estimates are
scored against (the simulator's ground truth, or motion capture). Within one panel each robot
has its own colour (one panel per method), so no two lines of a panel share a colour; a method
without an estimate gets a panel that says so instead of an empty frame.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes

from relloc.evaluation.report import ScenarioReport


def robot_colors(robots: list[str]) -> dict[str, tuple[float, ...]]:
    """A distinct colour per robot: matplotlib's ten-colour cycle, a continuous map beyond it."""
    if len(robots) <= 10:
        cycle = plt.get_cmap("tab10")
        return {r: cycle(k) for k, r in enumerate(robots)}
    cmap = plt.get_cmap("turbo")
    return {r: cmap(k / (len(robots) - 1)) for k, r in enumerate(robots)}


def _no_estimate(ax: Axes) -> None:
    ax.text(
        0.5, 0.75, "no estimate", transform=ax.transAxes, ha="center", va="center", fontsize=14,
        color="0.35", bbox={"facecolor": "white", "edgecolor": "0.7"},
    )


def _save(fig: plt.Figure, path: Path) -> Path:
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _reference(report: ScenarioReport) -> str:
    return report.reference or "the reference robot"


def plot_trajectories(report: ScenarioReport, path: Path, methods: list[str] | None = None) -> Path:
    """One panel per method: each robot's estimated relative trajectory over the truth."""
    names = methods or [m for m in report.methods if not m.endswith("_oracle")] or list(report.methods)
    fig, axes = plt.subplots(1, len(names), figsize=(5.5 * len(names), 5.4), squeeze=False)
    robots = sorted({r for m in report.methods.values() for r in m.paired})
    colors = robot_colors(robots)
    ref = _reference(report)
    empty: list[Axes] = []
    full: list[Axes] = []
    for ax, method in zip(axes[0], names, strict=True):
        m = report.methods[method]
        drawn = False
        for robot, p in sorted(m.paired.items()):
            if len(p.t):
                c = colors[robot]
                ax.plot(p.gt[:, 0], p.gt[:, 1], "-", color=c, lw=2.5, alpha=0.35)
                ax.plot(p.est[:, 0], p.est[:, 1], ".", color=c, ms=2, label=robot)
                drawn = True
        ax.plot([0], [0], "k*", ms=12, label=f"{ref} (reference)")
        (full if drawn else empty).append(ax)
        ax.set_title(f"{report.name}: {method}")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"x relative to {ref} (m)")
        ax.set_ylabel(f"y relative to {ref} (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    for ax in empty:  # the same extent as a panel with estimates, and a note
        if full:
            ax.set_xlim(full[0].get_xlim())
            ax.set_ylim(full[0].get_ylim())
        _no_estimate(ax)
    fig.suptitle(f"estimates (dots) over {report.truth_name} (thick lines), relative to {ref}")
    return _save(fig, path)


def plot_ape(report: ScenarioReport, path: Path) -> Path:
    """Box plots of APE after the warm-up, grouped by robot, one box per method with estimates.

    Boxes span the quartiles, whiskers reach 1.5 IQR, and every estimate beyond them is drawn as
    a dot (outliers shown, so the table's APE max is on the plot too). A method without any
    estimate is named in the legend as such."""
    methods = list(report.methods)
    robots = sorted({r for m in report.methods.values() for r in m.robots})
    cycle = plt.get_cmap("tab10")
    colors = {m: cycle(j % 10) for j, m in enumerate(methods)}
    data: dict[tuple[str, str], np.ndarray] = {}
    for method in methods:
        for robot in robots:
            p = report.methods[method].paired.get(robot)
            if p is not None:
                errs = p.errors[p.t >= report.t0 + report.warmup]
                if len(errs):
                    data[(method, robot)] = errs
    with_data = [m for m in methods if any((m, r) in data for r in robots)]
    width = min(0.8 / max(1, len(with_data)), 0.35)
    fig, ax = plt.subplots(figsize=(max(6.0, 0.8 * len(robots) * max(1, len(with_data))) + 2.5, 4.8))
    for i, robot in enumerate(robots):
        here = [m for m in with_data if (m, robot) in data]
        for j, method in enumerate(here):  # centred on the robot's tick, whatever is missing
            pos = i + (j - (len(here) - 1) / 2) * width
            bp = ax.boxplot(
                [data[(method, robot)]], positions=[pos], widths=width * 0.9, patch_artist=True,
                showfliers=True, flierprops={"marker": ".", "markersize": 3, "markeredgecolor": colors[method]},
            )
            for box in bp["boxes"]:
                box.set_facecolor(colors[method])
                box.set_alpha(0.6)
    for method in methods:
        label = method if method in with_data else f"{method}: no estimate"
        ax.plot([], [], "s", color=colors[method] if method in with_data else "0.7", label=label)
    ax.set_xticks(np.arange(len(robots)))
    ax.set_xticklabels(robots)
    ax.set_xlim(-0.6, len(robots) - 0.4)
    ax.set_ylabel(f"APE (m), position relative to {_reference(report)}")
    ax.set_title(
        f"{report.name}: APE after {report.warmup:g} s warm-up against {report.truth_name}\n"
        "boxes: quartiles; whiskers: 1.5 IQR; dots: outliers (all shown)",
        fontsize=10,
    )
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    return _save(fig, path)


def plot_ape_over_time(report: ScenarioReport, path: Path) -> Path:
    """APE against time, one panel per method, one colour per robot: convergence from the
    uniform prior, and where a method loses a robot."""
    methods = list(report.methods)
    robots = sorted({r for m in report.methods.values() for r in m.paired})
    colors = robot_colors(robots)
    fig, axes = plt.subplots(len(methods), 1, figsize=(8, 2.3 * len(methods) + 0.6), sharex=True, squeeze=False)
    for ax, method in zip(axes[:, 0], methods, strict=True):
        m = report.methods[method]
        drawn = False
        for robot, p in sorted(m.paired.items()):
            if len(p.t):
                ax.plot(p.t - report.t0, p.errors, lw=1, color=colors[robot], label=robot)
                drawn = True
        ax.axvline(report.warmup, color="k", ls="--", lw=1)
        if drawn:
            ax.set_yscale("log")
            ax.legend(fontsize=7, ncol=min(len(robots), 6), loc="upper right")
        else:
            _no_estimate(ax)
        ax.set_title(method, fontsize=10, loc="left")
        ax.set_ylabel("APE (m)")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time since the start of the run (s); dashed: end of the warm-up")
    fig.suptitle(f"{report.name}: APE against {report.truth_name}, relative to {_reference(report)}", fontsize=11)
    return _save(fig, path)
