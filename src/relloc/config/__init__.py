"""Team configuration: robots, reference robot, prior area, sensors and filter parameters.

The derivation: docs/explanation/internals.md, section ``relloc.config``.
"""

from __future__ import annotations

import math
import numbers
import tomllib
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from relloc.config.checks import Checked, ConfigError, build, with_numeric_overrides
from relloc.config.dump import drop_none, dump_toml
from relloc.config.filter import (
    AdaptiveConfig,
    FilterConfig,
    FilterKind,
    LikelihoodConfig,
    OdometryConfig,
    ResamplingConfig,
    SelfCalibrationConfig,
)
from relloc.config.moved import association_key_error
from relloc.config.sensors import (
    AssociationConfig,
    CameraConfig,
    PairCalibration,
    RobotConfig,
    TagConfig,
    UwbConfig,
)
from relloc.events import RangeEvent, pair_key

__all__ = [
    "AdaptiveConfig",
    "AssociationConfig",
    "CameraConfig",
    "ConfigError",
    "FilterConfig",
    "FilterKind",
    "LikelihoodConfig",
    "OdometryConfig",
    "PairCalibration",
    "ResamplingConfig",
    "RobotConfig",
    "RosDistro",
    "RosInterfaceKind",
    "SelfCalibrationConfig",
    "TagConfig",
    "TeamConfig",
    "UwbConfig",
    "with_numeric_overrides",
]


RosDistro = Literal["humble", "iron", "jazzy", "kilted", "lyrical", "rolling"]
"""The ROS 2 distributions relloc knows, oldest first (``rolling``: the newest ``rosbags`` ships;
their type stores: ``relloc.ros.distros``)."""

RosInterfaceKind = Literal["bridge", "rmw_zenoh"]
"""How the robots are on Zenoh live (``relloc.ros.interfaces``)."""


@dataclass(frozen=True)
class TeamConfig(Checked):
    """Everything the engine needs to know about a team."""

    robots: tuple[RobotConfig, ...]
    reference: str
    name: str = "team"
    area: tuple[float, float, float, float] = (-4.0, 4.0, -4.5, 4.5)
    """Prior box of every robot's position: xmin, xmax, ymin, ymax (m)."""
    uwb: UwbConfig = field(default_factory=UwbConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    """Cooperative detections: their noise and the association stage's gates."""
    mocap_topic: str = "/vrpn_client_node/{body}/pose"
    clock_offset: float | None = None
    """Header stamp minus receive time (s) for topics with zero stamps; ``None``: estimate it."""
    ros_interface: RosInterfaceKind = "bridge"
    """How the robots are on Zenoh live: zenoh-bridge-ros2dds or rmw_zenoh (``--ros-interface``
    overrides it; see ``relloc.ros.interfaces``)."""
    ros_distro: RosDistro = "jazzy"
    """The robots' ROS 2 distribution (``humble``, ``iron``, ``jazzy``, ``kilted``, ``lyrical``,
    ``rolling``; ``--ros-distro`` overrides it): the message layouts and type hashes relloc
    publishes live (``relloc.ros.distros``; received messages of any known layout are read)."""
    dimension: int = 2
    """The space the robots move in: 2 (ground robots, ``x, y``) or 3 (flying robots,
    ``x, y, z``: positions in 3D, yaw about z, roll and pitch taken as level)."""
    sensors: dict[str, dict[str, Any]] = field(default_factory=dict)
    """One raw ``[sensors.<kind>]`` table per sensor plug-in, parsed and checked by the plug-in's
    descriptor (:mod:`relloc.sensors`; a table of no registered sensor is a ``ConfigError``)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not all(isinstance(v, dict) for v in self.sensors.values()):
            raise ConfigError(
                f"sensors: each entry must be a [sensors.<kind>] table, got {self.sensors!r}"
            )
        names = [r.name for r in self.robots]
        if len(names) < 2:
            raise ConfigError("a team needs at least two robots")
        if len(set(names)) != len(names):
            raise ConfigError(f"robot names must be unique, got {names}")
        if self.reference not in names:
            raise ConfigError(f"reference robot {self.reference!r} is not one of {names}")
        xmin, xmax, ymin, ymax = self.area
        if not all(map(math.isfinite, self.area)) or not (xmin < xmax and ymin < ymax):
            raise ConfigError(f"area must be [xmin, xmax, ymin, ymax] with min < max: {self.area}")
        nodes = [n for r in self.robots for n in r.nodes]
        if len(set(nodes)) != len(nodes):
            raise ConfigError(f"each UWB node may be on one robot only: {nodes}")
        arms = {len(t.lever_arm) for r in self.robots for t in r.tags}
        if len(arms) > 1:
            raise ConfigError("every tag's lever_arm has the same dimension (2 or 3)")
        if self.dimension not in (2, 3):
            raise ConfigError(f"dimension must be 2 or 3, got {self.dimension!r}")

    @property
    def robot_names(self) -> tuple[str, ...]:
        return tuple(r.name for r in self.robots)

    @property
    def others(self) -> tuple[str, ...]:
        """Non-reference robots, in config order: the order of the filter state."""
        return tuple(r.name for r in self.robots if r.name != self.reference)

    def robot(self, name: str) -> RobotConfig:
        for r in self.robots:
            if r.name == name:
                return r
        raise KeyError(f"unknown robot {name!r}; the team is {list(self.robot_names)}")

    def range_nodes(self, event: RangeEvent) -> tuple[str, str]:
        """The transceivers of a range: the event's node ids, else the robots' first tags,
        else the robot names."""
        node_a = event.node_a or next(iter(self.robot(event.robot_a).nodes), event.robot_a)
        node_b = event.node_b or next(iter(self.robot(event.robot_b).nodes), event.robot_b)
        return node_a, node_b

    def robot_of_node(self, node: str) -> str | None:
        """The robot carrying UWB node ``node`` (``None``: no robot lists it)."""
        for r in self.robots:
            if node in r.nodes:
                return r.name
        return None

    def lever_arm(self, node: str) -> tuple[float, ...]:
        """Where node ``node`` sits in its robot's body frame (the origin for ``uwb_node``, or a
        node no robot lists: a range keyed by robot names)."""
        for r in self.robots:
            for tag in r.tags:
                if tag.node == node:
                    return tag.lever_arm
        return (0.0, 0.0)

    @property
    def multi_tag_robots(self) -> tuple[str, ...]:
        """Robots with two or more tags: ranges see their headings."""
        return tuple(r.name for r in self.robots if len(r.tag_list) >= 2)

    @property
    def has_lever_arms(self) -> bool:
        """Whether some tag sits off its robot's body origin."""
        return any(any(v != 0.0 for v in t.lever_arm) for r in self.robots for t in r.tags)

    def with_filter(self, **changes: Any) -> TeamConfig:
        """A copy with some filter parameters changed (:meth:`FilterConfig.with_changes`: each
        named by itself, whichever section holds it)."""
        return replace(self, filter=self.filter.with_changes(**changes))

    def with_modes(
        self,
        *,
        heading: str | None = None,
        bias: str | None = None,
        odom_scale: str | None = None,
        reference: str | None = None,
    ) -> TeamConfig:
        """A copy with the self-calibration modes set (``None`` keeps the config's): ``heading``
        ``compass|estimate``, ``bias`` ``calibrated|online``, ``odom_scale`` ``fixed|online``;
        ``reference`` makes another robot the reference. A mode outside its ``Literal`` is a
        :class:`ConfigError` (from :class:`FilterConfig` itself)."""
        changes: dict[str, Any] = {}
        if heading is not None:
            changes["heading_mode"] = heading
        if bias is not None:
            changes["bias_mode"] = bias
        if odom_scale is not None:
            changes["odom_scale_mode"] = odom_scale
        config = self.with_filter(**changes) if changes else self
        if reference is not None and reference != config.reference:
            if reference not in config.robot_names:
                raise ConfigError(
                    f"reference {reference!r} is not one of {list(config.robot_names)}"
                )
            config = replace(config, reference=reference)
        return config

    def with_robot(self, name: str, **changes: Any) -> TeamConfig:
        """A copy with one robot's settings changed."""
        robots = tuple(replace(r, **changes) if r.name == name else r for r in self.robots)
        return replace(self, robots=robots)

    # ------------------------------------------------------------------ (de)serialisation
    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TeamConfig:
        data = dict(data)
        try:
            robots_raw = data.pop("robots")
        except KeyError:
            raise ConfigError("the config has no [[robots]]") from None
        robots = []
        for i, raw in enumerate(robots_raw):
            raw = dict(raw)
            camera = build(CameraConfig, raw.pop("camera", {}), f"robots[{i}].camera")
            tags_raw = raw.pop("tags", [])
            if not isinstance(tags_raw, list | tuple) or not all(
                isinstance(t, dict) for t in tags_raw
            ):
                raise ConfigError(f"robots[{i}].tags must be a list of {{node, lever_arm}} tables")
            tags = tuple(
                build(TagConfig, dict(t), f"robots[{i}].tags[{k}]") for k, t in enumerate(tags_raw)
            )
            robots.append(
                build(RobotConfig, {**raw, "camera": camera, "tags": tags}, f"robots[{i}]")
            )
        uwb_raw = dict(data.pop("uwb", {}))
        pairs = {
            pair_key(*_split_pair(k)): build(PairCalibration, v, f"uwb.pairs.{k}")
            for k, v in uwb_raw.pop("pairs", {}).items()
        }
        uwb = build(UwbConfig, {**uwb_raw, "pairs": pairs}, "uwb")
        flt = FilterConfig.from_dict(data.pop("filter", {}))
        association_raw = data.pop("association", {})
        if not isinstance(association_raw, dict):
            raise ConfigError("association must be a table ([association])")
        for key in association_raw:
            error = association_key_error(key)
            if error is not None:
                raise ConfigError(error)
        association = build(AssociationConfig, association_raw, "association")
        if "area" in data:
            area = data["area"]
            numbers_only = isinstance(area, list | tuple) and all(
                isinstance(v, numbers.Real) and not isinstance(v, bool) for v in area
            )
            if not numbers_only or len(area) != 4:
                raise ConfigError(
                    f"area must be four numbers [xmin, xmax, ymin, ymax], got {area!r}"
                )
            data["area"] = tuple(float(v) for v in area)
        return build(
            cls,
            {
                **data,
                "robots": tuple(robots),
                "uwb": uwb,
                "filter": flt,
                "association": association,
            },
            "team",
        )

    @classmethod
    def load(cls, path: str | Path) -> TeamConfig:
        path = Path(path)
        try:
            with path.open("rb") as fh:
                data = tomllib.load(fh)
        except FileNotFoundError:
            raise ConfigError(f"config file not found: {path}") from None
        except OSError as exc:
            raise ConfigError(f"cannot read config {path}: {exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML: {exc}") from None
        uwb = data.get("uwb")
        if isinstance(uwb, dict) and isinstance(uwb.get("msg_dirs"), list):
            uwb["msg_dirs"] = [
                str(path.parent / d) if isinstance(d, str) else d for d in uwb["msg_dirs"]
            ]
        try:
            return cls.from_dict(data)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
        except (TypeError, ValueError, AttributeError) as exc:  # a table where a value belongs, ...
            raise ConfigError(f"{path}: malformed config ({type(exc).__name__}: {exc})") from None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["area"] = list(self.area)
        d["robots"] = [r.to_dict() for r in self.robots]
        d["uwb"]["pairs"] = {k: drop_none(asdict(v)) for k, v in self.uwb.pairs.items()}
        if not self.sensors:
            del d["sensors"]
        if self.dimension == 2:  # the default: configs of ground teams stay as they were
            del d["dimension"]
        return drop_none(d)

    def to_toml(self) -> str:
        return dump_toml(self.to_dict())

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_toml())


def _split_pair(key: str) -> tuple[str, str]:
    parts = key.split("-")
    if len(parts) != 2 or not all(parts):
        raise ConfigError(f"uwb.pairs key {key!r} must look like 'n_3-n_7'")
    return parts[0], parts[1]
