"""Navigation on the relative estimate: a robot follows a path given relative to the reference
robot, with the localizer's estimate as position feedback (the paper's last experiment).

* :mod:`~relloc.navigation.path`: waypoint paths and their TOML files;
* :mod:`~relloc.navigation.controller`: the path follower (pure pursuit, turning in place);
* :mod:`~relloc.navigation.safety`: when the robot must not move, and why;
* :mod:`~relloc.navigation.navigator`: estimate + odometry in, velocity command out;
* :mod:`~relloc.navigation.closed_loop`: the closed loop in the simulator (``relloc demo``, ``nav``);
* :mod:`~relloc.navigation.live`: ``relloc navigate`` over Zenoh (its command: :mod:`relloc.cli.navigation`;
  the simulated robots it can drive: :mod:`relloc.live.sim_robots`).

The names below are the pure, I/O-free core; the simulator loop, plots and Zenoh parts are
imported from their modules (they pull in matplotlib and zenoh).
"""

from relloc.navigation.controller import Command, ControllerConfig, PathFollower
from relloc.navigation.navigator import Feedback, Navigator
from relloc.navigation.path import PathError, WaypointPath, distance_to_polyline, load_path
from relloc.navigation.safety import SafetyConfig, SafetyGate, StopRecord

__all__ = [
    "Command",
    "ControllerConfig",
    "Feedback",
    "Navigator",
    "PathError",
    "PathFollower",
    "SafetyConfig",
    "SafetyGate",
    "StopRecord",
    "WaypointPath",
    "distance_to_polyline",
    "load_path",
]
