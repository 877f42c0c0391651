"""The large-team localizer: the formation from the range graph, then a Gaussian sum over it.

What a large team with odometry runs as ``pf`` where the config names ``kind = "range_graph"``:
the sampled filter's start from the uniform prior does not
scale past a few robots (``2(N-1)`` dimensions), its updates cost ``M`` particles times
``N(N-1)/2`` ranges, and the posterior it approximates is, after the start, a single narrow
bump. So:

* **Start** (``init_window`` of measurements, as the sampled filter): the shape from all
  pair ranges by classical MDS refined by SMACOF, turned to ``ROTATIONS`` evenly spaced angles
  about the reference and mirrored (:mod:`relloc.filter.range_shape`), one Gaussian per
  hypothesis whose covariance spans the gap to its neighbours along the rotation
  (``rotation_sigma`` half a step) and the shape's own error (``SHAPE_SIGMA``, or twice the
  fit's RMS residual if larger). Robots the range graph does not connect to the reference
  start at the reference with the prior box's variance. Detections of the window then weigh
  the hypotheses.
* **Cycle**: :class:`relloc.estimators.range_graph.filter.RangeGraphFilter`: odometry prediction,
  all ranges of a batch in one sparse information-form EKF update per hypothesis, the
  hypotheses that motion contradicts pruned.
* **Recovery**: when the divergence monitor finds it lost, the same start from the last
  ``init_window`` of measurements since the divergence began (the recovery's onset, as the
  sampled localizer re-anneals), the hypotheses weighed by their closeness to the last
  formation it trusted; only where they place no robot are hypotheses re-injected instead.
"""

from __future__ import annotations

import math

import numpy as np

from relloc.config import TeamConfig
from relloc.estimate import Estimate
from relloc.estimators.range_graph.filter import RangeGraphFilter
from relloc.events import RangeEvent
from relloc.filter.range_shape import orientation_hypotheses, shape_from_ranges, start_covariance
from relloc.filter.ranges import RangeBatch
from relloc.filter.state import StateLayout
from relloc.localizers.base import Measurement
from relloc.localizers.filtered import FilterLocalizer
from relloc.localizers.priors import ROTATION_FLOOR, covariance_floor

ROTATIONS = 36
"""Orientation hypotheses per handedness at the start (10 degrees apart)."""
SHAPE_SIGMA = 0.3
"""Smallest std (m per coordinate) of the start's shape."""
REFERENCE_SIGMA = 1.0
"""Recovery: how far (m per coordinate) a restarted hypothesis may be from the last trusted
formation and still be taken as its orientation."""


class RangeGraphLocalizer(FilterLocalizer):
    """Odometry + UWB ranges (+ detections) for a large team: a Gaussian sum started from the
    range graph (module docstring)."""

    method = "pf"
    filter: RangeGraphFilter

    def __init__(self, config: TeamConfig, *, seed: int = 0, method: str = "pf") -> None:
        layout = StateLayout(config.robot_names, config.reference)
        super().__init__(config, layout, seed=seed)
        self.method = method
        fc = config.filter
        self.range_model = fc.likelihood.range_model
        self.filter = RangeGraphFilter(
            layout,
            config.area,
            rng=self.rng,
            motion=self.motion,
            rotation_noise=fc.odometry.rotation_noise,
            rotation_floor=ROTATION_FLOOR,
        )
        self.filter.covariance_floor = covariance_floor(config, self.range_model)

    def _start(self, t: float, batch: list[Measurement]) -> Estimate | None:
        if not self._start_from(batch):
            return None
        self._started(t)
        self._since_shape(batch)
        return self._emit(t, self.filter.estimate())

    def _since_shape(self, batch: list[Measurement]) -> None:
        """The shape is that of the window's middle (the median range time): the odometry
        since then, not since the window's end, moves the hypotheses first (in the shared
        frame, so it already tells orientations apart)."""
        stamps = [m.t for m in batch if isinstance(m, RangeEvent)]
        if stamps:
            t_shape = float(np.median(stamps))
            self._anchor = {r: self.odometry.pose(r, t_shape) for r in self.layout.robots}

    def _start_from(self, batch: list[Measurement], reference: np.ndarray | None = None) -> bool:
        """Start the filter from ``batch``'s range graph (module docstring); with a
        ``reference`` formation ``(D,)``, weigh the hypotheses by their distance to it. False
        if the batch has no range that places a robot."""
        lay = self.layout
        ranges = [m for m in batch if isinstance(m, RangeEvent)]
        models = [
            b for b in self.models(ranges, self.filter, count=False) if isinstance(b, RangeBatch)
        ]
        if not models:
            return False
        ia = np.concatenate([b.index_a for b in models])
        ib = np.concatenate([b.index_b for b in models])
        z = np.concatenate([b.distance - b.bias for b in models])
        shape = shape_from_ranges(len(lay.robots), lay.index(lay.reference), ia, ib, z)
        others = np.array([lay.index(r) for r in lay.others], dtype=np.intp)
        if shape.measured == 0 or not shape.placed[others].any():
            return False
        formations = orientation_hypotheses(shape.relative[others], ROTATIONS, reflections=True)
        cov = start_covariance(formations, max(SHAPE_SIGMA, 2.0 * shape.rms), math.pi / ROTATIONS)
        unplaced = np.flatnonzero(~shape.placed[others])
        if unplaced.size:
            cols = np.concatenate([2 * unplaced, 2 * unplaced + 1])
            cov[:, cols, :] = 0.0
            cov[:, :, cols] = 0.0
            cov[:, cols, cols] = float(np.mean(self.filter.half_extent**2) / 3.0)
        logw = None
        if reference is not None:
            d2 = ((formations.reshape(formations.shape[0], -1) - reference) ** 2).sum(axis=1)
            logw = -0.5 * d2 / REFERENCE_SIGMA**2
        self.filter.initialize(formations, cov, logw)
        rest = self.models(
            [m for m in batch if not isinstance(m, RangeEvent)], self.filter, count=False
        )
        if rest:
            self.filter.update(rest)
        self.stats["graph_start_rms_mm"] = round(1000.0 * shape.rms)
        return True

    def _restart(self, recent: list[Measurement], reference: np.ndarray | None) -> bool:
        """Recovery's restart (:meth:`relloc.localizers.recovery.Recovery.recover` does the
        bookkeeping and picks ``recent``, the measurements since the divergence began): the
        start from their range graph, the hypotheses weighed by the last trusted formation
        ``reference``. False where they place no robot (the base then re-injects hypotheses
        about the estimate)."""
        if not self._start_from(recent, reference):
            return False
        self._since_shape(recent)
        self.stats["graph_restarts"] += 1
        return True
