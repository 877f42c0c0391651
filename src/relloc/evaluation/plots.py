"""Plots people in this field recognise, written as PNG files: relative trajectories over the
truth, APE distributions per robot and method (box plots), APE over time.

Every plot names the reference robot (positions are relative to it) and what the estimates are
scored against (the simulator's ground truth, or motion capture). Within one panel each robot
has its own colour (one panel per method), so no two lines of a panel share a colour; a method
without an estimate gets a panel that says so instead of an empty frame. No estimate is off a
trajectory panel: a far one is drawn at the edge and counted, and a method whose orientation is
unobservable shows its shapes as the evaluation aligns them.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from numpy.typing import NDArray

from relloc.evaluation.metrics import Paired
from relloc.evaluation.report import ScenarioReport

FloatArray = NDArray[np.float64]


def robot_colors(robots: list[str]) -> dict[str, tuple[float, ...]]:
    """A distinct colour per robot: matplotlib's ten-colour cycle, a continuous map beyond it."""
    if len(robots) <= 10:
        cycle = plt.get_cmap("tab10")
        return {r: cycle(k) for k, r in enumerate(robots)}
    cmap = plt.get_cmap("turbo")
    return {r: cmap(k / (len(robots) - 1)) for k, r in enumerate(robots)}


def _no_estimate(ax: Axes) -> None:
    ax.text(
        0.5,
        0.75,
        "no estimate",
        transform=ax.transAxes,
        ha="center",
        va="center",
        fontsize=14,
        color="0.35",
        bbox={"facecolor": "white", "edgecolor": "0.7"},
    )


def _save(fig: Figure, path: Path) -> Path:
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _reference(report: ScenarioReport) -> str:
    return report.reference or "the reference robot"


SHAPE_NOTE = "shape after one rotation/reflection for the run"
SANE_FACTOR = 3.0
"""Estimates within this many times the truth's extent (about its centre) widen the axes;
farther ones are drawn at the edge and counted, so one diverged robot does not shrink the rest."""


def _panel_pairs(report: ScenarioReport, method: str) -> tuple[dict[str, Paired], str]:
    """What a method's panel draws, and a note for its title: the estimates as scored, or, when
    most estimates after the warm-up leave the orientation unobservable (the positions are then
    moments over the ring of orientations, all near the reference), the published shapes after
    the shape APE's one rotation/reflection for the run."""
    m = report.methods[method]
    shaped = {r: p for r, p in m.shape_paired.items() if len(p.t)}
    if shaped and m.unobservable_fraction > 0.5:
        pct = 100 * m.unobservable_fraction
        return shaped, f"{SHAPE_NOTE}\n(orientation unobservable in {pct:.0f} % after the warm-up)"
    return {r: p for r, p in sorted(m.paired.items()) if len(p.t)}, ""


def _limits(truth: FloatArray, est: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Axes limits (lower, upper corners): the truth's box, widened to every estimate within
    :data:`SANE_FACTOR` times its extent, neither side under 0.6 of the other, plus a margin."""
    lo, hi = truth.min(axis=0), truth.max(axis=0)
    centre, span = (lo + hi) / 2, max(float(np.max(hi - lo)), 1.0)
    sane = est[np.all(np.abs(est - centre) <= SANE_FACTOR * span / 2, axis=1)]
    if len(sane):
        lo, hi = np.minimum(lo, sane.min(axis=0)), np.maximum(hi, sane.max(axis=0))
    size = np.maximum(hi - lo, max(0.6 * float(np.max(hi - lo)), 1.0))
    half = size / 2 + 0.06 * float(np.max(size))
    return (lo + hi) / 2 - half, (lo + hi) / 2 + half


def _draw_panel(
    ax: Axes, pairs: dict[str, Paired], colors: dict[str, tuple[float, ...]], name: str
) -> None:
    """The truth (thick lines), the estimates inside the limits (dots, gid ``estimate``) and
    those outside at the edge (crosses, gid ``estimate_clipped``) with a count per robot; 3D
    pairs in plan view (x, y)."""
    pairs = {r: Paired(p.t, p.est[:, :2], p.gt[:, :2], p.std) for r, p in pairs.items()}
    finite = {r: np.all(np.isfinite(p.est), axis=1) for r, p in pairs.items()}
    truth = np.concatenate([np.zeros((1, 2)), *(p.gt for p in pairs.values())])
    lo, hi = _limits(truth, np.concatenate([p.est[finite[r]] for r, p in pairs.items()]))
    off: list[str] = []
    for robot, p in pairs.items():
        c, est, gt = colors[robot], p.est[finite[robot]], p.gt[finite[robot]]
        ax.plot(p.gt[:, 0], p.gt[:, 1], "-", color=c, lw=2.5, alpha=0.35)
        inside = np.all((est >= lo) & (est <= hi), axis=1)
        ax.plot(*est[inside].T, ".", color=c, ms=2, label=robot, gid="estimate")
        if not inside.all():
            ax.plot(
                *np.clip(est[~inside], lo, hi).T,
                "x",
                color=c,
                ms=6,
                clip_on=False,
                gid="estimate_clipped",
            )
            far = float(np.max(np.linalg.norm(est[~inside] - gt[~inside], axis=1)))
            off.append(
                f"{name} {robot}: {int(np.sum(~inside))} points, up to {far:.0f} m from the truth"
            )
    if off:
        ax.plot([], [], "kx", label="off the axes, at the edge")
        ax.text(
            0.01, 0.01, "off the axes, drawn at the edge (x):\n" + "\n".join(off), transform=ax.transAxes,
            fontsize=7, va="bottom", bbox={"facecolor": "white", "edgecolor": "0.7", "alpha": 0.85},
        )  # fmt: skip
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])


def trajectory_figure(report: ScenarioReport, methods: list[str] | None = None) -> Figure:
    """One panel per method: each robot's estimated relative trajectory over the truth.

    Every estimate is visible: the axes include the truth and every estimate near it, and an
    estimate far out is drawn at the edge and counted in a note. A method whose orientation is
    mostly unobservable shows its shapes as the evaluation scores them (:func:`_panel_pairs`)."""
    names = (
        methods or [m for m in report.methods if not m.endswith("_oracle")] or list(report.methods)
    )
    fig, axes = plt.subplots(1, len(names), figsize=(5.5 * len(names), 5.6), squeeze=False)
    robots = sorted({r for m in report.methods.values() for r in m.paired})
    colors = robot_colors(robots)
    ref = _reference(report)
    empty: list[Axes] = []
    full: list[Axes] = []
    for ax, method in zip(axes[0], names, strict=True):
        pairs, note = _panel_pairs(report, method)
        if pairs:
            _draw_panel(ax, pairs, colors, method)
        ax.plot([0], [0], "k*", ms=12, label=f"{ref} (reference)")
        (full if pairs else empty).append(ax)
        ax.set_title(
            f"{report.name}: {method}" + (f": {note}" if note else ""), fontsize=10 if note else 12
        )
        ax.set_aspect("equal", adjustable="box")
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
    return fig


def plot_trajectories(report: ScenarioReport, path: Path, methods: list[str] | None = None) -> Path:
    """:func:`trajectory_figure` written to ``path``."""
    return _save(trajectory_figure(report, methods), path)


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
    fig, ax = plt.subplots(
        figsize=(max(6.0, 0.8 * len(robots) * max(1, len(with_data))) + 2.5, 4.8)
    )
    for i, robot in enumerate(robots):
        here = [m for m in with_data if (m, robot) in data]
        for j, method in enumerate(here):  # centred on the robot's tick, whatever is missing
            pos = i + (j - (len(here) - 1) / 2) * width
            bp = ax.boxplot(
                [data[(method, robot)]],
                positions=[pos],
                widths=width * 0.9,
                patch_artist=True,
                showfliers=True,
                flierprops={"marker": ".", "markersize": 3, "markeredgecolor": colors[method]},
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
    fig, axes = plt.subplots(
        len(methods), 1, figsize=(8, 2.3 * len(methods) + 0.6), sharex=True, squeeze=False
    )
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
    fig.suptitle(
        f"{report.name}: APE against {report.truth_name}, relative to {_reference(report)}",
        fontsize=11,
    )
    return _save(fig, path)
