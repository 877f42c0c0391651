"""Plots people in this field recognise: relative trajectories over ground truth, and APE
distributions per robot and method (box plots), written as PNG files."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from relloc.evaluation.report import ScenarioReport


def plot_trajectories(report: ScenarioReport, path: Path, methods: list[str] | None = None) -> Path:
    """One panel per method: each robot's estimated relative trajectory over the truth."""
    names = methods or [m for m in report.methods if not m.endswith("_oracle")]
    fig, axes = plt.subplots(1, len(names), figsize=(5.5 * len(names), 5.2), squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, method in zip(axes[0], names, strict=True):
        m = report.methods[method]
        for k, (robot, p) in enumerate(sorted(m.paired.items())):
            c = colors[k % len(colors)]
            if len(p.t):
                ax.plot(p.gt[:, 0], p.gt[:, 1], "-", color=c, lw=2.5, alpha=0.35)
                ax.plot(p.est[:, 0], p.est[:, 1], ".", color=c, ms=2, label=robot)
        ax.plot([0], [0], "k*", ms=12, label="reference")
        ax.set_title(f"{report.name}: {method}")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x relative to reference (m)")
        ax.set_ylabel("y relative to reference (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    fig.suptitle("estimates (dots) over motion capture (thick lines)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_ape(report: ScenarioReport, path: Path) -> Path:
    """Box plots of APE after warm-up, grouped by robot, one box per method."""
    methods = list(report.methods)
    robots = sorted({r for m in report.methods.values() for r in m.robots})
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(robots) * max(1, len(methods)) / 2), 4.5))
    width = 0.8 / max(1, len(methods))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for j, method in enumerate(methods):
        data, pos = [], []
        for i, robot in enumerate(robots):
            p = report.methods[method].paired.get(robot)
            if p is None:
                continue
            errs = p.errors[p.t >= report.t0 + report.warmup]
            if not len(errs):
                continue
            data.append(errs)
            pos.append(i + (j - (len(methods) - 1) / 2) * width)
        if data:
            bp = ax.boxplot(data, positions=pos, widths=width * 0.9, patch_artist=True, showfliers=False)
            for box in bp["boxes"]:
                box.set_facecolor(colors[j % len(colors)])
                box.set_alpha(0.6)
            ax.plot([], [], "s", color=colors[j % len(colors)], label=method)
    ax.set_xticks(np.arange(len(robots)))
    ax.set_xticklabels(robots)
    ax.set_ylabel("APE (m)")
    ax.set_title(f"{report.name}: APE after {report.warmup:g} s warm-up")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_ape_over_time(report: ScenarioReport, path: Path) -> Path:
    """APE against time for every method and robot: shows convergence from the prior."""
    fig, ax = plt.subplots(figsize=(8, 4))
    for method, m in report.methods.items():
        for robot, p in sorted(m.paired.items()):
            if len(p.t):
                ax.plot(p.t - report.t0, p.errors, lw=1, label=f"{method} {robot}")
    ax.axvline(report.warmup, color="k", ls="--", lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("time since the start of the run (s)")
    ax.set_ylabel("APE (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
