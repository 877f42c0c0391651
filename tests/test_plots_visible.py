"""The trajectory plot never hides an estimate: a team without odometry shows its shapes as the
evaluation scores them, and an estimate far off the truth is drawn at the edge and counted."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.axes import Axes

from relloc.engine import Engine
from relloc.evaluation.metrics import GroundTruth, Paired
from relloc.evaluation.plots import plot_trajectories, trajectory_figure
from relloc.evaluation.report import ScenarioReport, evaluate
from relloc.events import Event, OdometryEvent
from relloc.methods import build_pipeline
from relloc.simulator import multi_scenario


@pytest.fixture(scope="module")
def unobservable() -> ScenarioReport:
    """The pf method (the smoother, as auto picks it) on a 20 s team run with no odometry."""
    sim = multi_scenario(seed=0, duration=20)
    config = sim.config
    for robot in config.robot_names:
        config = config.with_robot(robot, odom_topic="")
    events: Iterator[Event] = (e for e in sim.events() if not isinstance(e, OdometryEvent))
    gt = GroundTruth(config.reference)
    engine = Engine([build_pipeline("pf", config)], truth_sinks=[gt.add])
    engine.run(events)
    return evaluate(engine, gt, "multi", 5.0)


def _points(ax: Axes, gid: str) -> np.ndarray:
    lines = [ln for ln in ax.get_lines() if ln.get_gid() == gid]
    return (
        np.concatenate([np.c_[ln.get_xdata(), ln.get_ydata()] for ln in lines])
        if lines
        else np.zeros((0, 2))
    )


def _inside(ax: Axes, points: np.ndarray) -> bool:
    (x0, x1), (y0, y1) = sorted(ax.get_xlim()), sorted(ax.get_ylim())
    eps = 1e-9 * max(x1 - x0, y1 - y0)
    x, y = points[:, 0], points[:, 1]
    return bool(np.all((x >= x0 - eps) & (x <= x1 + eps) & (y >= y0 - eps) & (y <= y1 + eps)))


def test_an_unobservable_orientation_plots_the_aligned_shapes(
    unobservable: ScenarioReport, tmp_path: Path
) -> None:
    m = unobservable.methods["pf"]
    assert m.unobservable_fraction == 1.0
    # the published positions are moments over the ring, all at the reference: drawn as they
    # are, every estimate hid under the reference's star
    assert all(np.allclose(p.est, 0.0) for p in m.paired.values())
    fig = trajectory_figure(unobservable, ["pf"])
    fig.canvas.draw()
    ax = fig.axes[0]
    title = ax.get_title()
    assert "shape after one rotation/reflection for the run" in title and "unobservable" in title
    drawn = _points(ax, "estimate")
    shaped = np.concatenate([p.est for p in m.shape_paired.values()])
    assert len(drawn) == len(shaped) > 100
    assert np.allclose(np.sort(drawn, axis=0), np.sort(shaped, axis=0))  # the scored shapes
    assert _inside(ax, drawn)
    assert not len(_points(ax, "estimate_clipped")) and not ax.texts
    plt.close(fig)
    assert plot_trajectories(unobservable, tmp_path / "t.png").stat().st_size > 10_000


def test_an_estimate_far_off_is_marked_at_the_edge_and_counted(
    unobservable: ScenarioReport,
) -> None:
    m = unobservable.methods["pf"]
    pairs = dict(m.paired)
    robot = sorted(pairs)[0]
    p = pairs[robot]
    est = p.gt.copy()
    est[:7] += [100.0, 0.0]  # seven points 100 m off
    est[7:10] += [2.0, 0.0]  # three points 2 m off: within reach, they widen the axes
    pairs[robot] = Paired(p.t, est, p.gt, p.std)
    for r in sorted(pairs)[1:]:
        pairs[r] = Paired(pairs[r].t, pairs[r].gt.copy(), pairs[r].gt, pairs[r].std)
    report = replace(unobservable, methods={"far": replace(m, results={}, paired=pairs)})
    fig = trajectory_figure(report)
    fig.canvas.draw()
    ax = fig.axes[0]
    inside, edge = _points(ax, "estimate"), _points(ax, "estimate_clipped")
    assert len(edge) == 7 and len(inside) == sum(len(q.t) for q in pairs.values()) - 7
    assert _inside(ax, inside) and _inside(ax, edge)
    assert np.allclose(edge[:, 0], ax.get_xlim()[1])  # on the right edge
    assert ax.get_xlim()[1] < 20.0  # the truth's axes, not stretched to 100 m
    text = " ".join(t.get_text() for t in ax.texts)
    assert f"far {robot}: 7 points" in text and "100 m" in text
    plt.close(fig)
