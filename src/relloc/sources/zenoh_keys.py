"""Which Zenoh keys carry a team's topics: the routes of the ingestion layer on the keys of
the ROS interface.

:func:`build_routes` puts the team's routes (:func:`~relloc.sources.ingest.team_routes`) on
their topic keys (:meth:`RosInterface.topic_key <relloc.ros.interfaces.RosInterface.topic_key>`:
``[<global prefix>/][<robot zenoh_scope>/]<topic without leading slash>`` on the bridge). A
route of two robots (a range topic) belongs to no single robot, so it is subscribed below the
scope of each of them (:func:`route_scopes`); a replay publishes it below the first. Motion
capture comes from no robot: with ``ground_truth`` it is subscribed below the global prefix
alone (:func:`truth_scopes`), where ``relloc replay --ground-truth`` and ``sim-robots`` put it.
"""

from __future__ import annotations

from relloc.config import ConfigError, TeamConfig
from relloc.ros.interfaces import RosInterface
from relloc.sensors import Route
from relloc.sensors.builtin import GROUND_TRUTH
from relloc.sources.ingest import team_routes

__all__ = ["build_routes", "route_scopes", "truth_scopes"]


def route_scopes(
    config: TeamConfig,
    *,
    odometry: bool = True,
    ranges: bool = True,
    detections: bool = True,
) -> list[tuple[Route, str]]:
    """Every route of the team with each namespace (robot ``zenoh_scope``) it arrives below:
    a robot's topics below its own, a range topic below each of its two robots'."""
    out: list[tuple[Route, str]] = []
    for route in team_routes(config, odometry=odometry, ranges=ranges, detections=detections):
        robots = (route.robot, route.robot_b) if route.robot_b else (route.robot,)
        for scope in dict.fromkeys(config.robot(r).zenoh_scope for r in robots):
            out.append((route, scope))
    return out


def truth_scopes(config: TeamConfig) -> list[tuple[Route, str]]:
    """Each robot's motion-capture route (``mocap_topic`` of its ``mocap_body``) with the
    namespace it arrives below: none (the motion-capture system is no robot's)."""
    routes = team_routes(config, odometry=False, ranges=False, detections=False, ground_truth=True)
    return [(r, "") for r in routes if r.kind == GROUND_TRUTH.kind]


def build_routes(
    config: TeamConfig,
    *,
    interface: RosInterface | None = None,
    prefix: str = "",
    odometry: bool = True,
    ranges: bool = True,
    detections: bool = True,
    ground_truth: bool = False,
) -> dict[str, Route]:
    """Every topic key the team's data arrives on (:meth:`RosInterface.topic_key
    <relloc.ros.interfaces.RosInterface.topic_key>`, the bridge's by default), mapped to its
    :class:`~relloc.sensors.Route`; with ``ground_truth``, the robots' motion capture too
    (:func:`truth_scopes`: for the viewer's truth; the engine keeps it from the localizers).

    Raises :class:`~relloc.config.ConfigError` if two routes would share one key (e.g. two robots
    configured with the same odometry topic and no scopes).
    """
    iface = interface or RosInterface()
    routes: dict[str, Route] = {}
    scoped = route_scopes(config, odometry=odometry, ranges=ranges, detections=detections)
    if ground_truth:
        scoped += truth_scopes(config)
    for route, scope in scoped:
        key = iface.topic_key(route.topic, prefix=prefix, scope=scope)
        old = routes.get(key)
        if old is not None and old != route:
            raise ConfigError(
                f"Zenoh key {key!r} would carry both {old.kind} of {old.robot} and "
                f"{route.kind} of {route.robot}; give the robots a zenoh_scope"
            )
        routes[key] = route
    return routes
