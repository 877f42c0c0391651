"""A run as one MCAP file of ROS 2 CDR messages, for Foxglove and RViz.

Per method and robot the estimates (``/relloc/<method>/<robot>/pose``,
``geometry_msgs/msg/PoseWithCovarianceStamped`` by :mod:`relloc.ros.estimate_msgs`),
per method the flags of each estimate (``/relloc/<method>/status``,
``diagnostic_msgs/msg/DiagnosticArray``), per robot the ground truth where the run has one
(``/relloc/truth/<robot>/pose``, ``geometry_msgs/msg/PoseStamped``, relative to the reference in
the first method's frame) and the ranges the run used (``/relloc/ranges/<a>/<b>``,
``sensor_msgs/msg/Range``). ``rosbags`` writes a rosbag2 folder; its single ``.mcap`` file,
self-contained (the message definitions are in it), is moved to the path asked for.
:class:`McapWriter` writes as the messages come: ``relloc serve --record`` feeds it live (no
truth there), :func:`write_mcap` a finished run's messages in log-time order.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from relloc.estimate import Estimate
from relloc.events import GroundTruthEvent, RangeEvent
from relloc.ros.estimate_msgs import estimate_pose_msg
from relloc.ros.messages import (
    POSE_STAMPED,
    POSE_WITH_COVARIANCE_STAMPED,
    RANGE,
    encode,
    pose_stamped_msg,
    range_msg,
    time_msg,
    typestore,
)

if TYPE_CHECKING:
    from relloc.engine import Engine
    from relloc.evaluation.report import ScenarioReport

__all__ = ["DIAGNOSTIC_ARRAY", "McapWriter", "estimate_records", "write_mcap"]

DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

Record = tuple[float, str, str, Any]
"""``(time in s, topic, message type, message)``."""


def pose_topic(method: str, robot: str) -> str:
    """The topic of ``method``'s estimates of ``robot``."""
    return f"/relloc/{method}/{robot}/pose"


def _status_msg(est: Estimate) -> Any:
    """The estimate's flags as a one-status ``DiagnosticArray`` (WARN unless its status is ok)."""
    types = typestore().types
    key_value = types["diagnostic_msgs/msg/KeyValue"]
    flags = {
        "orientation_observable": est.orientation_observable,
        "inconsistent": est.inconsistent,
        "recovering": est.recovering,
    }
    status = types["diagnostic_msgs/msg/DiagnosticStatus"](
        level=0 if est.status == "ok" else 1,
        name=f"relloc/{est.method}",
        message=est.status,
        hardware_id=est.reference,
        values=[key_value(key=k, value=str(v).lower()) for k, v in flags.items()],
    )
    header = types["std_msgs/msg/Header"](stamp=time_msg(est.t), frame_id=est.frame_id)
    return types[DIAGNOSTIC_ARRAY](header=header, status=[status])


def estimate_records(method: str, estimates: Iterable[Estimate]) -> list[Record]:
    """One pose per robot and one status per estimate of ``method``."""
    out: list[Record] = []
    for est in estimates:
        shown = est.published()  # once, not per robot
        for robot in shown.positions:
            msg = estimate_pose_msg(shown, robot)
            out.append((est.t, pose_topic(method, robot), POSE_WITH_COVARIANCE_STAMPED, msg))
        out.append((est.t, f"/relloc/{method}/status", DIAGNOSTIC_ARRAY, _status_msg(est)))
    return out


def _truth_records(report: ScenarioReport, engine: Engine) -> list[Record]:
    """The truth beside the estimates, from the first method with any: the evaluation's pairs
    (relative to the reference, in the frame of the estimate each is paired with)."""
    for p in engine.pipelines:
        m = report.methods.get(p.name)
        if m is None or not any(len(q.t) for q in m.paired.values()):
            continue
        frames = {e.t: e.frame_id for e in p.estimates}
        out: list[Record] = []
        for robot, q in m.paired.items():
            for t, position in zip(q.t.tolist(), q.gt.tolist(), strict=True):
                truth = GroundTruthEvent(t, robot, tuple(position), 0.0)  # z too, in 3D
                msg = pose_stamped_msg(truth, frame_id=frames[t])
                out.append((t, f"/relloc/truth/{robot}/pose", POSE_STAMPED, msg))
        return out
    return []


def _range_record(r: RangeEvent, distro: str) -> Record:
    return (
        r.t,
        f"/relloc/ranges/{r.robot_a}/{r.robot_b}",
        RANGE,
        range_msg(r, frame_id=f"{r.robot_a}/base_link", distro=distro),
    )


class McapWriter:
    """An MCAP file written as the messages come (``relloc serve --record``, and ``run --mcap``).

    :meth:`estimate` and :meth:`range` write one estimate's or range's messages at once; a
    channel is added on its topic's first message. ``rosbags`` writes into a temporary rosbag2
    folder beside ``path``; :meth:`close` (call it in a ``finally``: a context manager) finishes
    the file and moves it to ``path``, so ``path`` only ever holds a complete, readable file.
    """

    def __init__(self, path: Path, *, distro: str) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        self.distro = distro
        self.messages = 0
        """Messages written so far."""
        self._store = typestore(distro)
        self._conns: dict[str, Any] = {}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(prefix=".relloc-mcap-", dir=self.path.parent))
        self._bag = self._tmp / "bag"
        self._writer: Any = Writer(self._bag, version=9, storage_plugin=StoragePlugin.MCAP)
        try:
            self._writer.open()
        except Exception:
            shutil.rmtree(self._tmp, ignore_errors=True)
            raise

    def write(self, t: float, topic: str, msgtype: str, msg: Any) -> None:
        """Write one message, logged (and stamped by the caller) at ``t`` s."""
        if self._writer is None:
            raise ValueError(f"{self.path} is closed")
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._conns[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self._store
            )
        self._writer.write(conn, max(0, round(t * 1e9)), encode(msg, msgtype, self.distro))
        self.messages += 1

    def estimate(self, est: Estimate) -> None:
        """One pose per robot and the status of ``est`` (an engine sink)."""
        for record in estimate_records(est.method, (est,)):
            self.write(*record)

    def range(self, r: RangeEvent) -> None:
        """One range the methods were fed."""
        self.write(*_range_record(r, self.distro))

    def close(self) -> Path:
        """Finish the file and move it to :attr:`path` (idempotent)."""
        if self._writer is not None:
            writer, self._writer = self._writer, None
            try:
                writer.close()
                (written,) = self._bag.glob("*.mcap")
                shutil.move(written, self.path)
            finally:
                shutil.rmtree(self._tmp, ignore_errors=True)
        return self.path

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_mcap(
    path: Path,
    engine: Engine,
    report: ScenarioReport | None = None,
    *,
    distro: str,
    ranges: Sequence[RangeEvent] = (),
) -> Path:
    """Write every pipeline's estimates and status, the truth of ``report`` (if given) and
    ``ranges`` to the MCAP file ``path``, in ``distro``'s layouts and log-time order."""
    records: list[Record] = []
    for p in engine.pipelines:
        records += estimate_records(p.name, p.estimates)
    if report is not None:
        records += _truth_records(report, engine)
    records += [_range_record(r, distro) for r in ranges]
    records.sort(key=lambda r: r[0])  # stable: an estimate's poses before its status
    with McapWriter(path, distro=distro) as writer:
        for record in records:
            writer.write(*record)
    return path
