"""The multilateration baseline (the paper's Multi): least squares on the ranges present.

Keeps the latest bias-corrected range of every robot pair (of every tag pair where a robot has
several tags, each tag a point held at its lever arms' distance from its siblings,
:mod:`relloc.filter.tag_points`) and, at every batch, solves for the formation from those at
most ``max_age`` old (:mod:`relloc.filter.multilateration`), the gauge (rotation, reflection)
kept continuous with the previous solution; a robot is the rigid fit of its tags. No odometry, no filter: what
the ranges alone say at each instant.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.estimate import Estimate, position_of
from relloc.events import RangeEvent
from relloc.filter import multilateration
from relloc.filter.measurement import ModelContext
from relloc.filter.ranges import RangeBatch
from relloc.filter.tag_points import TagPoints
from relloc.localizers.base import Localizer, Measurement

FloatArray = NDArray[np.float64]


class MultilaterationLocalizer(Localizer):
    """Least-squares formation from the latest range of every pair, gauge kept continuous."""

    method = "multilateration"

    def __init__(self, config: TeamConfig, *, max_age: float = 0.5, seed: int = 0) -> None:
        super().__init__(config)
        self.max_age = max_age
        self._latest: dict[tuple[int, int], tuple[float, float]] = {}  # pair -> (t, corrected d)
        self._previous: FloatArray | None = None
        self.rng = np.random.default_rng(seed)
        self._context = ModelContext(config, self.layout, range_model="symmetric")
        self._points = TagPoints.of(config, self.layout)
        """The solved points: the robots, or a robot's tags where it has several."""

    def _step(self, t: float, batch: list[Measurement]) -> Estimate | None:
        ranges = [m for m in batch if isinstance(m, RangeEvent)]
        pts = self._points
        for model in RangeBatch.build(ranges, self._context):
            assert isinstance(model, RangeBatch)
            rows = zip(
                pts.points_of(model.index_a, model.nodes, 0),
                pts.points_of(model.index_b, model.nodes, 1),
                model.distance,
                model.bias,
                strict=True,
            )
            for a, b, d, bias in rows:
                self._latest[(int(a), int(b))] = (t, max(float(d - bias), 0.0))
        fresh = {k: d for k, (tk, d) in self._latest.items() if t - tk <= self.max_age}
        if not fresh:
            self.stats["no_estimate"] += 1
            return None
        rigid_a, rigid_b, rigid_d = pts.rigid
        keys = np.array([*fresh, *zip(rigid_a.tolist(), rigid_b.tolist(), strict=True)], np.intp)
        sol = multilateration.solve(
            pts.size,
            pts.reference_point,
            keys.reshape(-1, 2),
            np.concatenate([np.array(list(fresh.values())), rigid_d]),
            self._previous,
            self.rng,
            unfold=not pts.identity,
        )
        if sol is None:
            self.stats["no_estimate"] += 1
            return None
        self._previous = sol
        robots = sol if pts.identity else pts.poses(sol)[0]
        robots = robots - robots[pts.reference]  # the reference's first tag is the origin
        positions = {r: position_of(robots[self.layout.index(r)]) for r in self.layout.others}
        return Estimate(t, self.method, self.layout.reference, positions)
