"""A simulated robot team as an event source (the package's face: its public names).

The derivation: docs/explanation/internals.md, section ``relloc.simulator``.
"""

from relloc.simulator.camera_overlap import covisibility
from relloc.simulator.error_models import (
    ActuationModel,
    DetectionErrorModel,
    OdometryErrorModel,
    UwbErrorModel,
)
from relloc.simulator.kinematics import RobotMotion, SimObject
from relloc.simulator.runner import ARENA, Simulation
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
