"""The team live in Foxglove: a Foxglove WebSocket server beside Zenoh (``serve --foxglove``).

:class:`FoxgloveSink` is an engine sink. Its channels, below ``/<out prefix>`` (``/relloc``, or
``/relloc/<robot>`` on board), all of the first method:

* ``<robot>/pose``, one per non-reference robot: ``foxglove.PoseInFrame``, the fields of
  :func:`~relloc.ros.estimate_msgs.estimate_pose` (the one conversion the Zenoh poses use:
  same estimate, same numbers);
* ``poses``: ``foxglove.PosesInFrame``, the same poses of every non-reference robot in one
  message (the config's order): a layout names it whatever the robots' names;
* ``scene``: ``foxglove.SceneUpdate``: every robot, its 2-sigma covariance ellipse, the ranges
  heard since the last update as lines coloured by residual (measured minus estimated
  distance: green 0, red :data:`RED_RESIDUAL` m or more), rejected ones grey and labelled;
* ``flags`` (JSON, per estimate): the status line, orientation observable, recovering, the
  watchdog's ``inconsistent``, robots unseen, and per robot its covariance, std and, where
  motion capture reaches the engine (``truth_sinks``, ``serve --ground-truth``), its error
  ``error_m``: by name in ``robots`` and by index (the config's order of the non-reference
  robots, each entry naming its robot) in ``by_index``, which a plot's message path can name
  without the robots' names (``/relloc/flags.by_index[0].error_m``);
* ``status`` (JSON): what the server publishes on Zenoh as its status;
* ``<robot>/truth``: ``foxglove.PoseInFrame`` relative to the reference (world axes), advertised
  from the start when the sink is told motion capture comes (``truth``): a channel made while a
  client connects could miss it, and a client connected first would subscribe late;
* ``truth_poses``: ``foxglove.PosesInFrame``, every robot's ``truth`` in one message; advertised
  from the start (so a layout can name it), silent without motion capture.

Cost: a message is built only while a client subscribes to its channel (``has_sinks``), and at
most ``rate`` times a wall second per channel. ``foxglove`` is the ``viewer`` extra, imported
here only: :func:`require_sdk` says what to install.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from relloc.config import TeamConfig
from relloc.estimate import HEADING_FRAME, Estimate
from relloc.events import GroundTruthEvent, RangeEvent
from relloc.ros.cdr import split_stamp
from relloc.ros.estimate_msgs import estimate_pose

__all__ = ["RED_RESIDUAL", "FoxgloveSink", "parse_address", "require_sdk"]

RED_RESIDUAL = 0.5
"""Range residual (m) drawn fully red."""
SIGMAS = 2.0
"""The ellipses' half-axes in standard deviations."""
FLAGS_SCHEMA = {"title": "relloc.Flags", "type": "object"}
STATUS_SCHEMA = {"title": "relloc.Status", "type": "object"}
TRUTH_MAX_AGE = 0.5
"""A motion-capture pose older than this (s of header time) gives no error."""


def require_sdk() -> Any:
    """The ``foxglove`` module, or an ``ImportError`` that says how to install it."""
    try:
        import foxglove
    except ImportError as exc:
        raise ImportError(
            "--foxglove needs the Foxglove SDK: pip install 'relloc[viewer]'"
        ) from exc
    return foxglove


def parse_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` -> ``(host, port)``; the host defaults to 127.0.0.1 (this machine only)."""
    host, _, port = text.rpartition(":")
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f"--foxglove {text!r}: expected [HOST:]PORT") from None
    if not 0 <= number < 65536:
        raise ValueError(f"--foxglove {text!r}: port out of range")
    return host.strip("[]") or "127.0.0.1", number


def _stamp(t: float) -> Any:
    from foxglove.messages import Timestamp

    sec, nsec = split_stamp(t)  # as the Zenoh poses' headers
    return Timestamp(sec, nsec)


def _color(residual: float | None, rejected: bool) -> Any:
    from foxglove.messages import Color

    if rejected or residual is None:
        return Color(r=0.5, g=0.5, b=0.5, a=0.8)
    red = min(1.0, abs(residual) / RED_RESIDUAL)
    return Color(r=red, g=1.0 - red, b=0.0, a=1.0)


class FoxgloveSink:
    """A Foxglove WebSocket server and the channels of the module docstring.

    Call it with each estimate (an engine sink), :meth:`range` with each range fed to the
    methods, :meth:`truth` with motion capture, :meth:`publish_status` with the server's
    status. ``rejections`` counts the first method's rejected events: a range after which it
    rose is drawn rejected. :meth:`close` stops the server. Not thread-safe: the engine thread
    calls it all.
    """

    def __init__(
        self,
        config: TeamConfig,
        address: str,
        *,
        prefix: str = "relloc",
        method: str = "pf",
        rate: float = 10.0,
        rejections: Callable[[], int] | None = None,
        clock: Callable[[], float] = time.monotonic,
        truth: bool = False,
    ) -> None:
        foxglove = require_sdk()
        from foxglove.channels import (
            PoseInFrameChannel,
            PosesInFrameChannel,
            SceneUpdateChannel,
        )

        if rate <= 0:
            raise ValueError(f"--foxglove-rate must be positive, got {rate}")
        host, port = parse_address(address)
        self.config = config
        self.method = method
        self.period = 1.0 / rate
        self.prefix = "/" + prefix.strip("/")
        self._rejections = rejections
        self._clock = clock
        self._context = foxglove.Context()  # its own: two servers in a process stay apart
        self.poses = {
            r: PoseInFrameChannel(f"{self.prefix}/{r}/pose", context=self._context)
            for r in config.others
        }
        self.all_poses = PosesInFrameChannel(f"{self.prefix}/poses", context=self._context)
        self.truth_poses = PosesInFrameChannel(f"{self.prefix}/truth_poses", context=self._context)
        self.scene = SceneUpdateChannel(f"{self.prefix}/scene", context=self._context)
        self.flags = foxglove.Channel(
            f"{self.prefix}/flags", schema=FLAGS_SCHEMA, context=self._context
        )
        self.status = foxglove.Channel(
            f"{self.prefix}/status", schema=STATUS_SCHEMA, context=self._context
        )
        self.truths: dict[str, Any] = {
            r: PoseInFrameChannel(f"{self.prefix}/{r}/truth", context=self._context)
            for r in (config.others if truth else ())
        }
        """Each robot's truth channel, made up front with ``truth`` (none without)."""
        self._truth: dict[str, GroundTruthEvent] = {}
        self._sent: dict[str, float] = {}
        self._ranges: dict[tuple[str, str], tuple[RangeEvent, bool]] = {}
        self._pending: tuple[RangeEvent, int] | None = None
        self.server = foxglove.start_server(
            name=f"relloc {config.name}", host=host, port=port, context=self._context
        )
        self.host = host
        self.port: int = self.server.port

    @property
    def topics(self) -> list[str]:
        """Every topic advertised now."""
        channels = [*self.poses.values(), self.all_poses, self.truth_poses, self.scene]
        channels += [self.flags, self.status]
        return [c.topic() for c in [*channels, *self.truths.values()]]

    # ---------------------------------------------------------------- inputs
    def __call__(self, estimate: Estimate) -> None:
        """An estimate: poses, scene and flags, each only if subscribed and due."""
        if estimate.method != self.method:
            return
        self._settle()
        now = self._clock()
        shown = estimate.published()
        for robot, channel in self.poses.items():
            if robot in shown.positions and self._due(channel, now):
                channel.log(self._pose(shown, robot))
        if self._due(self.all_poses, now):
            self.all_poses.log(self._poses(shown))
        if self._due(self.scene, now):
            self.scene.log(self._scene(shown))
            self._ranges.clear()
        if self._due(self.flags, now):
            self.flags.log(self._flags(estimate, shown))

    def range(self, event: RangeEvent) -> None:
        """A range the methods are fed (before they are): kept for the next scene."""
        self._settle()
        if not self.scene.has_sinks():
            self._ranges.clear()
            return
        count = self._rejections() if self._rejections is not None else 0
        self._pending = (event, count)
        self._ranges[(event.robot_a, event.robot_b)] = (event, False)

    def truth(self, event: GroundTruthEvent) -> None:
        """A motion-capture pose (an engine truth sink): kept for the errors and
        ``truth_poses``, and on the robot's own channel where the sink was made with ``truth``."""
        self._truth[event.robot] = event
        if event.robot not in self.poses:
            return
        now = self._clock()
        relative = self._relative_truth(event.robot, event.t)
        channel = self.truths.get(event.robot)
        if relative is not None and channel is not None and self._due(channel, now):
            channel.log(self._truth_pose(event, relative))
        if self._due(self.truth_poses, now):
            self.truth_poses.log(self._truth_poses(event.t))

    def publish_status(self, status: dict[str, Any]) -> None:
        """The server's status, as it goes out on Zenoh."""
        if self.status.has_sinks():
            self.status.log(json.dumps(status, default=_jsonable))

    def close(self) -> None:
        """Stop the server (idempotent)."""
        server, self.server = self.server, None
        if server is not None:
            server.stop()

    # ---------------------------------------------------------------- building
    def _due(self, channel: Any, now: float) -> bool:
        if not channel.has_sinks():
            return False
        topic = channel.topic()
        if now - self._sent.get(topic, -math.inf) < self.period:
            return False
        self._sent[topic] = now
        return True

    def _settle(self) -> None:
        """Mark the last range rejected if the localizer's rejections rose since it came."""
        if self._pending is None or self._rejections is None:
            return
        event, count = self._pending
        self._pending = None
        if self._rejections() > count:
            key = (event.robot_a, event.robot_b)
            if self._ranges.get(key, (None,))[0] is event:
                self._ranges[key] = (event, True)

    def _pose(self, shown: Estimate, robot: str) -> Any:
        from foxglove.messages import PoseInFrame

        p = estimate_pose(shown, robot)  # the one conversion: relloc.ros.estimate_msgs
        return PoseInFrame(
            timestamp=_stamp(p.t), frame_id=p.frame_id, pose=_pose_of(p.x, p.y, p.z, p.yaw)
        )

    def _poses(self, shown: Estimate) -> Any:
        from foxglove.messages import PosesInFrame

        poses = [estimate_pose(shown, r) for r in self.poses if r in shown.positions]
        return PosesInFrame(
            timestamp=_stamp(shown.t),
            frame_id=poses[0].frame_id if poses else shown.frame_id,
            poses=[_pose_of(p.x, p.y, p.z, p.yaw) for p in poses],
        )

    def _truth_poses(self, t: float) -> Any:
        """Every robot's motion-capture pose fresh at ``t``, relative to the reference."""
        from foxglove.messages import PosesInFrame

        poses = []
        for robot in self.poses:
            relative = self._relative_truth(robot, t)
            if relative is not None:
                z = float(relative[2]) if len(relative) > 2 else 0.0
                yaw = float(self._truth[robot].yaw)
                poses.append(_pose_of(float(relative[0]), float(relative[1]), z, yaw))
        return PosesInFrame(timestamp=_stamp(t), frame_id=self.config.reference, poses=poses)

    def _scene(self, shown: Estimate) -> Any:
        from foxglove.messages import (
            Color,
            CylinderPrimitive,
            LinePrimitive,
            Point3,
            SceneEntity,
            SceneEntityDeletion,
            SceneEntityDeletionType,
            SceneUpdate,
            SpherePrimitive,
            TextPrimitive,
            Vector3,
        )

        stamp = _stamp(shown.t)
        where: dict[str, tuple[float, float, float]] = {shown.reference: (0.0, 0.0, 0.0)}
        for r, pos in shown.positions.items():
            where[r] = (float(pos[0]), float(pos[1]), float(pos[2]) if len(pos) > 2 else 0.0)
        entities = []
        for robot, (x, y, z) in where.items():
            unseen = robot in shown.unseen
            rgb = (0.9, 0.6, 0.1) if unseen else (0.0, 0.4, 0.9)
            colour = Color(r=rgb[0], g=rgb[1], b=rgb[2], a=1.0)
            cylinders = []
            cov = shown.covariance(robot)
            if cov is not None:
                values, vectors = np.linalg.eigh(cov[:2, :2])
                half = SIGMAS * np.sqrt(np.clip(values, 0.0, None))
                angle = math.atan2(vectors[1, 1], vectors[0, 1])
                cylinders.append(
                    CylinderPrimitive(
                        pose=_pose_of(x, y, z, angle),
                        size=Vector3(x=2 * half[1], y=2 * half[0], z=0.01),
                        bottom_scale=1.0,
                        top_scale=1.0,
                        color=Color(r=rgb[0], g=rgb[1], b=rgb[2], a=0.25),
                    )
                )
            entities.append(
                SceneEntity(
                    timestamp=stamp,
                    frame_id=shown.frame_id,
                    id=f"robot/{robot}",
                    spheres=[
                        SpherePrimitive(
                            pose=_pose_of(x, y, z, 0.0),
                            size=Vector3(x=0.3, y=0.3, z=0.3),
                            color=colour,
                        )
                    ],
                    cylinders=cylinders,
                    texts=[
                        TextPrimitive(
                            pose=_pose_of(x, y, z + 0.4, 0.0),
                            billboard=True,
                            font_size=14.0,
                            scale_invariant=True,
                            color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
                            text=robot + (" (unseen)" if unseen else ""),
                        )
                    ],
                )
            )
        for (a, b), (event, rejected) in self._ranges.items():
            if a not in where or b not in where:
                continue
            pa, pb = np.array(where[a]), np.array(where[b])
            residual = event.distance - float(np.linalg.norm(pa - pb))
            mid = (pa + pb) / 2
            label = f"{event.distance:.2f} m" + (" rejected" if rejected else f" ({residual:+.2f})")
            entities.append(
                SceneEntity(
                    timestamp=stamp,
                    frame_id=shown.frame_id,
                    id=f"range/{a}/{b}",
                    lines=[
                        LinePrimitive(
                            thickness=3.0 if not rejected else 1.5,
                            scale_invariant=True,
                            points=[Point3(x=p[0], y=p[1], z=p[2]) for p in (pa, pb)],
                            color=_color(residual, rejected),
                        )
                    ],
                    texts=[
                        TextPrimitive(
                            pose=_pose_of(mid[0], mid[1], mid[2], 0.0),
                            billboard=True,
                            font_size=11.0,
                            scale_invariant=True,
                            color=_color(residual, rejected),
                            text=label,
                        )
                    ],
                )
            )
        return SceneUpdate(
            deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)],
            entities=entities,
        )

    def _flags(self, estimate: Estimate, shown: Estimate) -> str:
        robots: dict[str, Any] = {}
        for r in shown.positions:
            cov = shown.covariance(r)
            entry: dict[str, Any] = {
                "std_m": None if cov is None else round(shown.std(r), 4),
                "cov_xx": None if cov is None else float(cov[0, 0]),
                "cov_xy": None if cov is None else float(cov[0, 1]),
                "cov_yy": None if cov is None else float(cov[1, 1]),
                "unseen_s": shown.unseen.get(r),
            }
            truth = self._relative_truth(r, estimate.t)
            if truth is not None and estimate.frame == HEADING_FRAME:
                entry["error_m"] = round(
                    float(np.linalg.norm(estimate.position(r)[:2] - truth[:2])), 4
                )
            robots[r] = entry
        sec, nsec = split_stamp(estimate.t)
        return json.dumps(
            {
                "timestamp": {"sec": sec, "nsec": nsec},
                "t": estimate.t,
                "method": estimate.method,
                "frame_id": shown.frame_id,
                "status": estimate.status,
                "orientation_observable": estimate.orientation_observable,
                "recovering": estimate.recovering,
                "inconsistent": estimate.inconsistent,
                "unseen": sorted(estimate.unseen),
                "n_modes": estimate.n_modes,
                "mode_weight": round(estimate.mode_weight, 3),
                "ess": None if estimate.ess is None else round(estimate.ess, 1),
                "robots": robots,
                "by_index": [{"robot": r, **robots.get(r, {})} for r in self.poses],
            }
        )

    def _relative_truth(self, robot: str, t: float) -> np.ndarray | None:
        """``robot``'s motion-capture position minus the reference's (world axes), if both
        are fresh at ``t``."""
        mine, ref = self._truth.get(robot), self._truth.get(self.config.reference)
        if mine is None or ref is None:
            return None
        if abs(mine.t - t) > TRUTH_MAX_AGE or abs(ref.t - t) > TRUTH_MAX_AGE:
            return None
        a, b = np.asarray(mine.position, float), np.asarray(ref.position, float)
        n = min(len(a), len(b))
        return np.asarray(a[:n] - b[:n], dtype=float)

    def _truth_pose(self, event: GroundTruthEvent, relative: np.ndarray) -> Any:
        from foxglove.messages import PoseInFrame

        z = float(relative[2]) if len(relative) > 2 else 0.0
        return PoseInFrame(
            timestamp=_stamp(event.t),
            frame_id=self.config.reference,
            pose=_pose_of(float(relative[0]), float(relative[1]), z, float(event.yaw)),
        )


def _pose_of(x: float, y: float, z: float, yaw: float) -> Any:
    from foxglove.messages import Pose, Quaternion, Vector3

    half = yaw / 2.0
    return Pose(
        position=Vector3(x=float(x), y=float(y), z=float(z)),
        orientation=Quaternion(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)),
    )


def _jsonable(value: Any) -> Any:
    from relloc.sinks.zenoh_sink import _jsonable as zenoh_jsonable

    return zenoh_jsonable(value)
