"""How often the robots of a simulation see a common object at the same time.

A property of a scenario's motion and camera geometry (ideal cameras, true poses), not of any
run of the filter: what detection-based scenarios are tuned with.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

from relloc.events import pair_key
from relloc.simulator.error_models import camera_view, in_view
from relloc.simulator.runner import Simulation

__all__ = ["covisibility"]


def covisibility(sim: Simulation, dt: float = 0.2) -> dict[str, float]:
    """How often pairs of robots see a common object at the same time (ideal cameras).

    Checked on a grid of period ``dt`` with the true poses (no misses, no noise). Returns the
    fraction of time for each robot pair (key ``pair_key(a, b)``), plus ``"any"``: the
    fraction of time at least one pair co-sees an object, and ``"mean_pairs"``: the mean
    number of co-seeing pairs. For a commanded robot only the closed-loop run so far counts.
    """
    if not sim.sim_objects:
        return {"any": 0.0, "mean_pairs": 0.0}
    t_end = sim._runner.t_sim if sim.commanded else sim.duration
    times = np.arange(0.0, t_end + 1e-9, dt)
    seen = {}
    for name in sim.robots:
        x, y, yaw, _ = sim._runner.traj[name].evaluate(times)
        d, bearing = camera_view(x, y, yaw, sim.camera, sim._obj_xyz)
        seen[name] = in_view(d, bearing, sim.camera, sim.detection_model.min_range)
    result: dict[str, float] = {}
    count = np.zeros(times.size)
    for a, b in combinations(sim.robots, 2):
        both = (seen[a] & seen[b]).any(axis=1)
        result[pair_key(a, b)] = float(both.mean())
        count += both
    result["any"] = float((count > 0).mean())
    result["mean_pairs"] = float(count.mean())
    return result
