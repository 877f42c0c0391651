"""The sensor descriptor: everything relloc knows about one kind of sensor, in one object.

A :class:`Sensor` bundles what used to be spread over the ingestion layer, the bag and Zenoh
sources, the replay and the message faults, each of which now asks the descriptor of a topic's
kind instead of comparing kind names:

* **Identity and counters**: ``kind`` names the sensor; it is the :attr:`Route.kind` of its
  topics, the key its events are counted under (``IngestStats.events``) and the clock group of
  its streams (:class:`~relloc.sources.clock.HeaderClock` kinds). ``event`` is its event type.
* **Routes from the team config**: :meth:`robot_routes` (per robot, in robot order),
  :meth:`team_routes` (after every robot's) and :meth:`object_routes` say which topics carry it
  and what each needs to be converted. A plug-in reads its own table of the config
  (``TeamConfig.sensors[kind]``) and validates it itself (:meth:`settings`).
* **ROS messages**: ``msgtypes`` it reads, ``msg_types`` the definitions to add to the type
  store (a plug-in's own ``.msg``), :meth:`fast` (a fixed-layout fast path per layout, :mod:`relloc.ros.cdr`),
  :meth:`convert` (decoded message -> event) and :meth:`message` (event -> message, for replay).
* **Its measurement model** (``model``, a class of :mod:`relloc.filter.measurement`, registered
  with :mod:`relloc.filter.registry` along with the sensor; ``None``: the localizer consumes the
  event without one, or a stage turns it into another's). Whether a sensor's events count as
  "heard from" for unseen robots, its stream key and whether it ranges are the model's hooks.
* **How sources treat it**: ``switch`` (the source switch that turns it off), ``required``
  (a bag must hold each of its topics), ``warn_empty``, ``wake`` (whether its stamp decides if a
  live message wakes the engine) and ``essential`` (every server subscribes to it: a replay waits
  for its subscribers).
* **Optional hooks**: ``faulted`` with :meth:`fault_event` / :meth:`write_back`
  (:mod:`relloc.live.message_faults`),
  :meth:`config_warnings` and :meth:`bag_check` (what a bag source reports about it).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Protocol

from relloc.config import CameraConfig, ConfigError, RobotConfig, TeamConfig

if TYPE_CHECKING:
    from relloc.events import Event
    from relloc.filter.measurement import MeasurementModel
    from relloc.ros.distros import Layout

__all__ = ["Conversion", "Route", "Sensor", "Switch"]

Switch = Literal["odometry", "ranges", "detections", "ground_truth"]
"""The source switches (``team_routes(config, odometry=..., ...)``) a sensor can be under."""


@dataclass(frozen=True)
class Route:
    """How the messages of one topic become events: the sensor ``kind`` and what its
    conversion needs."""

    topic: str
    kind: str
    msgtypes: tuple[str, ...]
    """Message types tried in order (an unspecified detection format accepts two)."""
    robot: str
    """The robot (or motion-capture object) the events concern; a range's first robot."""
    what: str
    """What the topic is, for messages: ``"odometry of r1"``, ``"UWB ranges n_1-n_2"``..."""
    robot_b: str = ""
    node_a: str = ""
    node_b: str = ""
    camera: CameraConfig | None = None
    zero_stamps: bool = False
    """Stamp every message from its receive time (``odom_zero_stamps``): its stamps are untrusted."""
    stamped: bool = True
    """Whether its messages start with a ``std_msgs/Header`` (a UWB driver's may not); no clock is
    learnt from a topic without."""
    sigma: tuple[float, float] = (0.0, 0.0)
    """A sighting's range (m) and bearing (rad) noise."""
    params: Any = None
    """A plug-in's own settings for this topic (parsed from its table of the team config)."""

    @property
    def restamped(self) -> bool:
        """Whether its messages are stamped from their receive time: stamps untrusted, or none."""
        return self.zero_stamps or not self.stamped


class _Counts(Protocol):
    rejected: Counter[str]
    repeated_ranges: int


class Conversion(Protocol):
    """What a sensor's :meth:`Sensor.convert` may ask of the ingestion layer's converter."""

    @property
    def stats(self) -> _Counts: ...

    def reject(self, reason: str, stream: str, detail: str = "") -> None:
        """Count (and maybe log) a message dropped for ``reason``."""
        ...

    def memory(self, kind: str) -> dict[Any, Any]:
        """A dictionary the sensor ``kind`` may keep state in for one pass over the data."""
        ...


class Sensor:
    """Base of the sensor descriptors (module docstring); the defaults are a sensor with no
    routes, no fast path, no replay encoding and no faults."""

    kind: ClassVar[str]
    event: ClassVar[type]
    msgtypes: ClassVar[tuple[str, ...]]
    """Every ROS message type its topics may carry."""
    msg_types: ClassVar[Mapping[str, Any]] = {}
    """Message definitions (a ``rosbags`` types dict, :func:`rosbags.typesys.get_types_from_msg`)
    registered with relloc's type store with the sensor."""
    model: ClassVar[type[MeasurementModel] | None] = None
    switch: ClassVar[Switch | None] = None
    """The source switch that leaves it out (``None``: always read)."""
    required: ClassVar[bool] = True
    """A bag must hold each of its topics (else a pair without a topic simply has none)."""
    warn_empty: ClassVar[bool] = True
    """A bag topic of it without messages is a warning."""
    wake: ClassVar[Literal["odometry", "measurement"] | None] = None
    """How a live source judges whether its message must wake the engine (by the wake rule's
    odometry or measurement bound); ``None``: always wakes it."""
    essential: ClassVar[bool] = False
    """Every server subscribes to it: a replay waits for its subscribers."""
    faulted: ClassVar[bool] = False
    """A replay's message faults work on its messages (:meth:`fault_event`, :meth:`write_back`)."""

    # ------------------------------------------------------------------ config and routes
    def settings(self, config: TeamConfig) -> Any:
        """This sensor's settings from its table of the team config (``TeamConfig.sensors[kind]``).
        A plug-in parses and checks its table here, raising :class:`~relloc.config.ConfigError`
        naming the key; by default a sensor takes no table (the built-ins' settings are keys of
        the robots and of ``uwb``)."""
        if self.kind in config.sensors:
            raise ConfigError(f"sensors.{self.kind}: this sensor takes no table of its own")
        return None

    def robot_routes(self, config: TeamConfig, robot: RobotConfig) -> list[Route]:
        """The routes of ``robot``'s own topics of this sensor."""
        return []

    def team_routes(self, config: TeamConfig) -> list[Route]:
        """The routes that belong to no single robot's turn (pairs, observers' templates)."""
        return []

    def object_routes(self, config: TeamConfig, objects: Sequence[str]) -> list[Route]:
        """The routes of extra named bodies (motion capture), whatever the switches."""
        return []

    # ------------------------------------------------------------------ messages
    def fast(self, payload: bytes, layout: Layout) -> tuple[float, ...] | None:
        """``(stamp, fields...)`` straight from the CDR bytes of a message in ``layout`` (one
        of its type's definitions, :mod:`relloc.ros.distros`), or ``None``: the full decoder
        decodes the payload then (or says why not)."""
        return None

    def convert(
        self,
        route: Route,
        stream: str,
        msg: Any,
        fast: tuple[float, ...] | None,
        stamp: float,
        ingest: Conversion,
    ) -> Event | list[Event] | None:
        """The event of one message (decoded ``msg``, or the :meth:`fast` fields) stamped
        ``stamp`` (or its events, for a message holding several); ``None`` if unusable
        (counted through ``ingest``)."""
        raise NotImplementedError

    def writes(self, route: Route) -> bool:
        """Whether this sensor makes the messages of ``route`` (replay of events, message
        faults): a topic of one of its own types, not of a driver's own type it only reads."""
        return route.msgtypes[0] in self.msgtypes

    def message(self, event: Any) -> Any:
        """``event`` as the ROS message its topic carries (replay of events), or ``None`` if
        this sensor is not replayed from events."""
        return None

    def channel_key(self, route: Route) -> Hashable:
        """What tells its topics apart for replay: the key :meth:`event_key` gives an event."""
        return route.robot

    def event_key(self, event: Any) -> Hashable:
        """The :meth:`channel_key` of the topic ``event`` goes out on."""
        return event.robot

    # ------------------------------------------------------------------ faults
    def fault_event(self, route: Route, msg: Any, t: float) -> Event:
        """The event a message fault works on, of a decoded message timed ``t`` (``faulted``)."""
        raise NotImplementedError

    def write_back(self, msg: Any, before: Any, after: Any) -> Any:
        """``msg`` with the fields a fault changed (``before`` -> ``after``; not the stamp)."""
        return msg

    # ------------------------------------------------------------------ simulation
    def simulate(self, sim: Any, t0: float, t1: float) -> list[Event]:
        """The events it produces in ``(t0, t1]`` of a :class:`relloc.simulator.Simulation`
        (``sim.true_pose(robot, t)``, ``sim.config``), for a plug-in the simulator does not
        know. The built-in sensors are simulated by the simulator itself: none here."""
        return []

    # ------------------------------------------------------------------ bag checks
    def config_warnings(self, config: TeamConfig) -> list[str]:
        """What a bag source warns about before it looks at the bag."""
        return []

    def bag_check(
        self, config: TeamConfig, bag_topics: Iterable[str], resolved: Iterable[Route]
    ) -> tuple[list[str], list[str]]:
        """After its routes were resolved against a bag (``resolved``: those the bag has):
        ``(its topics the bag has but the team does not read, warnings)``."""
        return [], []
