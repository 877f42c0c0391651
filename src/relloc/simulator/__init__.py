"""A simulated robot team as an event source (the package's face: its public names).

What it is
----------
A small, deterministic 2D world in which differential-drive robots move (on the paper's
patterns, or under velocity commands for closed-loop navigation) and their sensors produce
exactly the events a real recording or a live team produces (:mod:`relloc.events`):

* odometry at 20 Hz per robot, in the robot's *own* odometry frame (the frame is the robot's
  pose at ``t = 0``), integrated from a noisy twist: a per-robot wheel-scale error, velocity
  noise and a small gyro bias make it drift like real wheel odometry (about 1 % of the path);
* UWB ranges for every pair of transceivers (:class:`UwbErrorModel`): a per-pair bias, an
  error that depends smoothly on each end's heading relative to the bearing to the other end
  (antenna pattern and body occlusion), Gaussian noise, positive NLOS spikes and dropouts, each
  pair at its own rate with its own phase and jitter;
* detections of static objects by each robot's forward camera at about 5 Hz
  (:class:`DetectionErrorModel`), in the robot body frame, with depth noise growing with
  distance and occasional misses;
* ground truth (the "motion capture") at 20 Hz in the world frame.

Why it is built this way
------------------------
* **Deterministic and stable under change.** Every random quantity comes from its own
  sub-stream of ``numpy.random.default_rng``, keyed by the seed, what it is and whose it is
  (e.g. the noise of the UWB pair ``n_1-n_3``). Switching detections on, adding a robot or
  lengthening the run therefore does not change the UWB noise of an existing pair. All sensor
  time stamps and noise draws are fixed when the simulation is built, so the step-wise API
  (:meth:`Simulation.advance`) returns the same events however the run is cut into steps.
* **Exact kinematics.** Motion is a sequence of constant-twist segments (straight lines, turns
  in place, circular arcs), integrated in closed form; ground truth has no integration error,
  and the odometry error is exactly the error model's, nothing else.
* **Truthful configuration.** :attr:`Simulation.config` is the team configuration a user would
  write for this team: UWB node ids, the true per-pair biases and the true heading offset of
  each odometry frame (the "compass" the paper assumes). What a real team would *not* know
  (wheel scales, gyro biases, the orientation-dependent range error) stays in the simulation,
  exposed as attributes for tests and calibration experiments.

Modules
-------
:mod:`.error_models` (sensor and actuation errors), :mod:`.kinematics` (objects, motions,
trajectories, the paper's patterns), :mod:`.runner` (:class:`Simulation`, the event source),
:mod:`.scenarios`, :mod:`.streams` (seeded random streams).

Scenarios
---------
:func:`multi_scenario` is the paper's five-robot experiment in the 8 m x 9 m arena (a static
reference robot and four robots on a triangle, an X, a circle and a rectangle),
:func:`single_scenario` the two-robot single-range experiment, and :func:`nav_scenario` the
multi team with one robot driven by velocity commands.
"""

from relloc.simulator.error_models import (
    ActuationModel,
    DetectionErrorModel,
    OdometryErrorModel,
    UwbErrorModel,
)
from relloc.simulator.kinematics import RobotMotion, SimObject
from relloc.simulator.runner import ARENA, Simulation, covisibility
from relloc.simulator.scenarios import multi_scenario, nav_scenario, single_scenario

__all__ = [
    "ARENA",
    "ActuationModel",
    "DetectionErrorModel",
    "OdometryErrorModel",
    "RobotMotion",
    "SimObject",
    "Simulation",
    "UwbErrorModel",
    "covisibility",
    "multi_scenario",
    "nav_scenario",
    "single_scenario",
]
