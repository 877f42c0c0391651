"""What a robot's own sensors produced (``relloc.events.measured_by``): what it publishes on
board, and what a partition of it withholds from its teammates."""

from __future__ import annotations

from relloc.events import (
    GroundTruthEvent,
    HeightEvent,
    OdometryEvent,
    RangeEvent,
    SightingEvent,
    measured_by,
)


def test_a_robot_measures_its_odometry_height_sightings_and_the_ranges_it_initiates() -> None:
    odom = OdometryEvent(0.0, "a", 0.0, 0.0, 0.0)
    ranged = RangeEvent(0.0, "a", "b", 3.0)
    seen = SightingEvent(0.0, "b", "a", range=2.0, bearing=None)
    height = HeightEvent(0.0, "b", 1.0)
    truth = GroundTruthEvent(0.0, "a", (0.0, 0.0))
    assert [measured_by(e, "a") for e in (odom, ranged, seen, height, truth)] == [
        True,
        True,
        False,
        False,
        False,
    ]
    assert [measured_by(e, "b") for e in (odom, ranged, seen, height, truth)] == [
        False,
        False,
        True,
        True,
        False,
    ]
