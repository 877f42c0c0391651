"""Pairing with motion capture in other gauges than an estimate's frame.

:func:`associate_shapes` pairs the published shapes (the formation in its declared gauge), to
be aligned once for the run; :func:`body_frame_paired` the positions in the reference robot's
body frame, the gauge-free relative position that needs no alignment.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import replace

import numpy as np

from relloc.estimate import BODY_FRAME, HEADING_FRAME, Estimate
from relloc.evaluation.metrics import GroundTruth, Paired, _to_body, associate


def associate_shapes(
    estimates: Sequence[Estimate],
    gt: GroundTruth,
    robots: Iterable[str],
    rotation: float = 0.0,
) -> dict[str, Paired]:
    """Like :func:`associate`, for the published shapes (the formation in its declared gauge,
    :attr:`Estimate.shape`) instead of the positions: align these once for the run
    (:func:`align` ``"run"``), as multilateration's formation is, for the shape APE."""
    shaped = [
        replace(est, positions=dict(est.shape), frame=HEADING_FRAME)
        for est in estimates
        if est.shape
    ]
    return associate(shaped, gt, robots, rotation)


def body_frame_paired(
    estimates: Sequence[Estimate],
    gt: GroundTruth,
    robots: Iterable[str],
    reference_yaws: Iterable[tuple[float, float]],
) -> dict[str, Paired]:
    """Every robot's estimated position in the *reference robot's body frame* (where robot j
    is as the reference would see it: x forward, y left; in 3D its yaw-only frame, z up, the
    height difference kept) paired with the same in the truth.

    This is the gauge-free relative position: no shared heading frame, no alignment. The
    estimate's frame turns into the body frame by the reference's heading in it, its odometry
    yaw at the estimate's time (``reference_yaws``: ``(t, yaw)`` in its odometry track's frame,
    :attr:`relloc.localizers.base.Localizer.odometry_yaws`) plus, where the method estimates
    headings, the published heading of the reference's odometry frame (its drift); the truth
    by the reference's motion-capture yaw. Estimates without a recorded yaw are left out.
    """
    yaw_at = dict(reference_yaws)
    out: dict[str, Paired] = {}
    ref = gt.reference
    for robot in robots:
        t, e, g, s = [], [], [], []
        for est in estimates:
            body = est.frame == BODY_FRAME  # already in the body frame
            if robot not in est.positions or (est.t not in yaw_at and not body):
                continue
            truth = gt.relative_at(robot, est.t, est.dimension)
            pose = gt.pose_at(ref, est.t)
            if truth is None or pose is None:
                continue
            heading = (
                0.0
                if body
                else yaw_at[est.t] + (est.headings[ref][0] if ref in est.headings else 0.0)
            )
            t.append(est.t)
            e.append(_to_body(est.positions[robot], heading))
            g.append(_to_body(truth, pose[2]))
            s.append(est.std(robot))
        dim = len(e[0]) if e else 2
        out[robot] = Paired(
            np.array(t), np.array(e).reshape(-1, dim), np.array(g).reshape(-1, dim), np.array(s)
        )
    return out
