"""The UTIAS MRCLAM data sets as an event source: wheel odometry, teammate sightings, Vicon.

MRCLAM (Leung, Halpern, Barfoot, Liu, IJRR 2011) is the standard benchmark of cooperative
localization: five iRobot Creates, a monocular camera each that reads the barcodes of the
teammates and of static landmarks, and Vicon ground truth. A data set folder holds, per robot
``i``, whitespace-separated text files with ``#`` comment lines:

* ``Robot{i}_Odometry.dat``: ``time, forward velocity, angular velocity`` (about 70 Hz). The
  source integrates it (each command holds until the next sample) into a pose in the robot's
  own odometry frame, starting at the origin with yaw 0: nothing comes from the ground truth.
* ``Robot{i}_Measurement.dat``: ``time, barcode, range, bearing`` in the observer's body
  frame. ``Barcodes.dat`` maps subject numbers to barcodes; subjects ``1..5`` are the robots,
  the others static landmarks, which relloc ignores (it is infrastructure-free; counted as
  ``landmark_sightings``).
* ``Robot{i}_Groundtruth.dat``: ``time, x, y, orientation`` (Vicon, about 65 Hz), for
  evaluation only.

The team config (``configs/mrclam/``) names the robots ``robot1`` .. ``robot5`` after the
subject numbers. Each sighting carries the camera's noise, a range sigma that grows with the
distance and a bearing sigma (:data:`RANGE_SIGMA`, :data:`RANGE_SIGMA_PER_M`,
:data:`BEARING_SIGMA`): docs/explanation/mrclam.md says where the values come from.
"""

from __future__ import annotations

import heapq
import math
import sys
import warnings
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from relloc.config import TeamConfig
from relloc.events import Event, GroundTruthEvent, OdometryEvent, SightingEvent

FloatArray = NDArray[np.float64]

RANGE_SIGMA = 0.06
"""Range noise of the MRCLAM camera at zero distance (m)."""
RANGE_SIGMA_PER_M = 0.02
"""Growth of the range noise with the distance (m per m): 0.08 m at 1 m, 0.14 m at 4 m."""
BEARING_SIGMA = math.radians(1.0)
"""Bearing noise (rad): the barcode's bearing is good to 0.4 deg, the rest covers the time
stamp of a sighting taken while the robots turn."""

ODOMETRY_DELAY = 0.24
"""Seconds between an odometry sample's stamp and the motion it reports (s): the files hold
the velocity *commands* of the iRobot Creates, which the drive follows about a quarter of a
second later. The source stamps each sample this much later."""

ROBOT_SUBJECTS = range(1, 6)
"""Subject numbers of the robots in ``Barcodes.dat``."""


MALFORMED_SHOWN = 5
"""Malformed rows a file's warning names by line; :attr:`MrclamSource.malformed` holds all."""


class MrclamError(Exception):
    """The folder is not an MRCLAM data set (the message says what is missing)."""


def is_mrclam(path: str | Path) -> bool:
    """Whether ``path`` is a folder that holds an MRCLAM data set."""
    p = Path(path)
    return p.is_dir() and (p / "Barcodes.dat").is_file() and (p / "Robot1_Odometry.dat").is_file()


@dataclass(frozen=True)
class MalformedRow:
    """One row of a ``.dat`` file the reader skipped: where it is and why."""

    file: str
    line: int
    """1-based line number in the file."""
    reason: str
    """``columns`` (another column count), ``text`` (a field that is no number) or
    ``nonfinite`` (NaN or infinity)."""


def read_table(path: Path, columns: int, malformed: list[MalformedRow] | None = None) -> FloatArray:
    """The numeric rows of an MRCLAM ``.dat`` file as ``(n, columns)`` (comments skipped).

    A row with another column count, a field that is no number, NaN or infinity (a garbage
    line, a file cut off mid-line) is skipped and appended to ``malformed``; without that list
    it is an error. A missing file, or one without a single valid row, is a
    :class:`MrclamError` naming it. Clean files take numpy's parser, damaged ones a
    line-by-line pass; both read the same numbers."""
    if not path.is_file():
        raise MrclamError(f"{path} is missing")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter(
                "ignore"
            )  # numpy's "no data" warning: an empty file is an error below
            rows = np.loadtxt(path, comments="#", ndmin=2)
    except ValueError:
        rows = None
    if rows is not None and rows.size and rows.shape[1] == columns and np.isfinite(rows).all():
        return rows
    skipped: list[MalformedRow] = []
    good = _read_rows(path, columns, skipped)
    if not len(good):
        raise MrclamError(
            f"{path} holds no valid {columns}-column rows"
            + (f" ({len(skipped)} malformed)" if skipped else "")
        )
    if skipped and malformed is None:
        first = skipped[0]
        raise MrclamError(f"{path}: line {first.line} is malformed ({first.reason})")
    if malformed is not None:
        malformed.extend(skipped)
    return good


def _read_rows(path: Path, columns: int, skipped: list[MalformedRow]) -> FloatArray:
    """The valid rows of ``path``, line by line; the others appended to ``skipped``."""
    rows: list[list[float]] = []
    with path.open(errors="replace") as f:
        for number, line in enumerate(f, start=1):
            fields = line.split("#", 1)[0].split()
            if not fields:
                continue
            reason = None
            if len(fields) != columns:
                reason = "columns"
            else:
                try:
                    values = [float(v) for v in fields]
                except ValueError:
                    reason = "text"
                else:
                    if not all(math.isfinite(v) for v in values):
                        reason = "nonfinite"
            if reason is None:
                rows.append(values)
            else:
                skipped.append(MalformedRow(path.name, number, reason))
    return np.array(rows, dtype=float).reshape(-1, columns)


def integrate_odometry(table: FloatArray) -> FloatArray:
    """Poses ``(n, 3)`` (x, y, yaw) at each sample's time from velocity commands ``(n, 3)``
    (time, v, w): each command holds until the next sample (exact arcs, not Euler steps)."""
    t, v, w = table[:, 0], table[:, 1], table[:, 2]
    n = len(t)
    out = np.zeros((n, 3))
    dt = np.diff(t)
    x = y = yaw = 0.0
    for k in range(1, n):  # one robot's samples, not particles: a plain loop
        d, vk, wk = dt[k - 1], v[k - 1], w[k - 1]
        turn = wk * d
        if abs(turn) < 1e-9:
            x += vk * d * math.cos(yaw + 0.5 * turn)
            y += vk * d * math.sin(yaw + 0.5 * turn)
        else:
            radius = vk / wk
            x += radius * (math.sin(yaw + turn) - math.sin(yaw))
            y -= radius * (math.cos(yaw + turn) - math.cos(yaw))
        yaw = math.remainder(yaw + turn, math.tau)
        out[k] = (x, y, yaw)
    return out


@dataclass
class MrclamStats:
    """What the source read and left out."""

    counts: Counter[str]

    @property
    def rejected(self) -> dict[str, int]:
        return {
            k.removeprefix("rejected_"): v
            for k, v in self.counts.items()
            if k.startswith("rejected_")
        }

    def as_dict(self) -> dict[str, int]:
        return dict(self.counts)


class MrclamSource:
    """An MRCLAM data set folder as time-ordered events for ``config``'s robots."""

    def __init__(
        self,
        folder: str | Path,
        config: TeamConfig,
        *,
        ground_truth: bool = True,
        sightings: str = "both",
    ) -> None:
        if sightings not in ("both", "range", "bearing"):
            raise ValueError(f"sightings must be both, range or bearing, not {sightings!r}")
        self.folder = Path(folder)
        self.name = self.folder.name
        self.use = sightings
        """What of each sighting to pass on: ``both``, ``range`` (bearing left out) or ``bearing``."""
        if not is_mrclam(self.folder):
            raise MrclamError(
                f"{self.folder} is not an MRCLAM data set (no Barcodes.dat / Robot1_Odometry.dat)"
            )
        self.config = config
        self.ground_truth = ground_truth
        self.warnings: list[str] = []
        self.stats = MrclamStats(Counter())
        self.robots = {self._subject(r.name): r.name for r in config.robots}
        self.malformed: list[MalformedRow] = []
        """Every row skipped as malformed, with its file, line and reason."""
        barcodes = self._table("Barcodes.dat", 2)
        self.barcode_subject = {int(b): int(s) for s, b in barcodes}
        self.odometry = {i: self._table(f"Robot{i}_Odometry.dat", 3) for i in self.robots}
        self.measurements = {i: self._table(f"Robot{i}_Measurement.dat", 4) for i in self.robots}
        self.truth = {i: self._table(f"Robot{i}_Groundtruth.dat", 4) for i in self.robots}
        starts = [t[0, 0] for t in self.odometry.values() if len(t)]
        ends = [t[-1, 0] for t in self.odometry.values() if len(t)]
        if not starts:
            raise MrclamError(f"{self.folder}: no odometry")
        for i, name in self.robots.items():  # where each robot's odometry comes from
            if len(self.odometry[i]) and not self.config.robot(name).odom_topic:
                self.config = self.config.with_robot(name, odom_topic=f"Robot{i}_Odometry.dat")
        self.start_time = float(min(starts))
        self.end_time = float(max(ends))

    def _table(self, name: str, columns: int) -> FloatArray:
        """``name``'s valid rows; its malformed ones counted, kept and summed up in a warning."""
        before = len(self.malformed)
        rows = read_table(self.folder / name, columns, self.malformed)
        skipped = self.malformed[before:]
        if skipped:
            self.stats.counts["rejected_malformed_row"] += len(skipped)
            shown = ", ".join(f"line {m.line} ({m.reason})" for m in skipped[:MALFORMED_SHOWN])
            more = (
                f" and {len(skipped) - MALFORMED_SHOWN} more"
                if len(skipped) > MALFORMED_SHOWN
                else ""
            )
            self.warnings.append(f"{name}: {len(skipped)} malformed rows skipped: {shown}{more}")
        return rows

    def initial_poses(self) -> dict[str, tuple[float, float, float]]:
        """Every robot's Vicon pose at its first odometry sample: the start of an oracle
        baseline (``ekf_oracle``), never given to relloc's filters."""
        out = {}
        for i, name in self.robots.items():
            truth, t = self.truth[i], self.odometry[i][0, 0] + ODOMETRY_DELAY
            k = min(int(np.searchsorted(truth[:, 0], t)), len(truth) - 1)
            out[name] = (float(truth[k, 1]), float(truth[k, 2]), float(truth[k, 3]))
        return out

    @staticmethod
    def _subject(name: str) -> int:
        digits = name.removeprefix("robot")
        if not digits.isdigit() or int(digits) not in ROBOT_SUBJECTS:
            raise MrclamError(
                f"MRCLAM robots are named robot1 .. robot5 (subject numbers), not {name!r}"
            )
        return int(digits)

    @property
    def duration(self) -> float:
        return self.end_time - self.start_time

    def __iter__(self) -> Iterator[Event]:
        streams: list[Iterator[Event]] = [self._odometry(i) for i in self.robots]
        streams += [self._sightings(i) for i in self.robots]
        if self.ground_truth:
            streams += [self._truth(i) for i in self.robots]
        yield from heapq.merge(*streams, key=lambda ev: ev.t)

    def _odometry(self, subject: int) -> Iterator[OdometryEvent]:
        table, name = self.odometry[subject], self.robots[subject]
        poses = integrate_odometry(table)
        for (t, v, w), (x, y, yaw) in zip(table.tolist(), poses.tolist(), strict=True):
            self.stats.counts["odometry"] += 1
            yield OdometryEvent(t + ODOMETRY_DELAY, name, x, y, yaw, v, w)

    def _sightings(self, subject: int) -> Iterator[SightingEvent]:
        name = self.robots[subject]
        for t, code, r, b in self.measurements[subject].tolist():
            target = self.barcode_subject.get(int(code))
            if target is None:
                self.stats.counts["rejected_unknown_barcode"] += 1
                continue
            if target not in ROBOT_SUBJECTS:
                self.stats.counts["landmark_sightings"] += 1
                continue
            if target not in self.robots:
                self.stats.counts["rejected_robot_not_in_team"] += 1
                continue
            self.stats.counts["sightings"] += 1
            yield SightingEvent(
                t,
                name,
                self.robots[target],
                None if self.use == "bearing" else r,
                None if self.use == "range" else b,
                RANGE_SIGMA + RANGE_SIGMA_PER_M * r,
                BEARING_SIGMA,
                "camera",
            )

    def _truth(self, subject: int) -> Iterator[GroundTruthEvent]:
        name = self.robots[subject]
        for t, x, y, yaw in self.truth[subject].tolist():
            yield GroundTruthEvent(t, name, (x, y), yaw)


# ---------------------------------------------------------------------- the reference rule
GROUND_TRUTH_GAP = 0.5
"""A Vicon gap longer than this (s) is a dropout: the time in it is not covered (Vicon samples
come every 15 ms; Dataset 6 has two gaps of 2 s in robot4's file)."""

COVERAGE_TOLERANCE = 1.0
"""Robots whose ground truth covers the run to within this (s) of the longest tie."""


@dataclass(frozen=True)
class ReferenceCandidate:
    """One robot's claim to be a session's reference: what the rule compares."""

    robot: str
    ground_truth_s: float
    """Seconds of the run (first to last odometry sample of the team) that the robot's Vicon
    ground truth covers, dropouts longer than :data:`GROUND_TRUTH_GAP` left out."""
    sightings: int
    """Robot-to-robot sightings the robot takes part in, as observer or as the one seen."""


def ground_truth_coverage(
    truth: FloatArray, start: float, end: float, gap: float = GROUND_TRUTH_GAP
) -> float:
    """Seconds of ``[start, end]`` covered by the ground truth's time stamps ``truth[:, 0]``:
    the overlap of every step between two samples no longer than ``gap`` with the run."""
    t = np.sort(np.asarray(truth, dtype=float)[:, 0])
    if len(t) < 2:
        return 0.0
    lo, hi = np.maximum(t[:-1], start), np.minimum(t[1:], end)
    steps = np.diff(t) <= gap
    return float(np.sum(np.clip(hi - lo, 0.0, None)[steps]))


def reference_candidates(
    folder: str | Path, robots: tuple[str, ...] | None = None
) -> list[ReferenceCandidate]:
    """Every robot of the session ``folder`` (``robots``, else those with an odometry file),
    best reference first by :func:`choose_reference`'s rule."""
    folder = Path(folder)
    if not is_mrclam(folder):
        raise MrclamError(
            f"{folder} is not an MRCLAM data set (no Barcodes.dat / Robot1_Odometry.dat)"
        )
    if robots is None:
        subjects = [i for i in ROBOT_SUBJECTS if (folder / f"Robot{i}_Odometry.dat").is_file()]
    else:
        subjects = [MrclamSource._subject(name) for name in robots]
    skipped: list[MalformedRow] = []  # the rule reads what the source reads: malformed rows skipped
    odometry = {i: read_table(folder / f"Robot{i}_Odometry.dat", 3, skipped) for i in subjects}
    start = min(float(t[0, 0]) for t in odometry.values())
    end = max(float(t[-1, 0]) for t in odometry.values())
    barcodes = read_table(folder / "Barcodes.dat", 2, skipped)
    subject_of = {int(b): int(s) for s, b in barcodes}
    sightings: Counter[int] = Counter()
    for i in subjects:
        for code in read_table(folder / f"Robot{i}_Measurement.dat", 4, skipped)[:, 1]:
            target = subject_of.get(int(code))
            if target in subjects and target != i:
                sightings[i] += 1
                sightings[target] += 1
    found = [
        ReferenceCandidate(
            f"robot{i}",
            ground_truth_coverage(
                read_table(folder / f"Robot{i}_Groundtruth.dat", 4, skipped), start, end
            ),
            sightings[i],
        )
        for i in subjects
    ]
    longest = max(c.ground_truth_s for c in found)
    return sorted(
        found,
        key=lambda c: (
            c.ground_truth_s < longest - COVERAGE_TOLERANCE,
            -c.sightings,
            MrclamSource._subject(c.robot),
        ),
    )


def choose_reference(folder: str | Path, robots: tuple[str, ...] | None = None) -> str:
    """The reference robot of an MRCLAM session by a rule that needs no run of the filter:

    1. the robot whose Vicon ground truth covers the longest part of the run (from the team's
       first to its last odometry sample; dropouts over :data:`GROUND_TRUTH_GAP` not counted),
       so that every estimate can be scored; robots within :data:`COVERAGE_TOLERANCE` of the
       longest tie;
    2. of those, the one that takes part in the most robot-to-robot sightings (made or
       received): the estimates are in its frame, and each sighting it is in ties a teammate
       to that frame directly;
    3. then the lowest subject number.

    Dataset 6: robot1's ground truth ends 128 s early and robot4's has two 2 s dropouts;
    robot2, robot3 and robot5 cover the whole run, and robot5 is in the most sightings
    (1913, against 1693 and 1673): ``robot5``."""
    return reference_candidates(folder, robots)[0].robot


def main(argv: list[str] | None = None) -> int:
    """``python -m relloc.sources.mrclam --reference FOLDER``: print the session's reference
    robot by :func:`choose_reference`'s rule (``--explain``: every robot's figures too)."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m relloc.sources.mrclam",
        description="Print the reference robot of an MRCLAM session by the rule of "
        "relloc.sources.mrclam.choose_reference: the longest ground truth, then the most sightings.",
    )
    parser.add_argument(
        "--reference", required=True, metavar="FOLDER", help="an MRCLAM data set folder"
    )
    parser.add_argument(
        "--explain", action="store_true", help="list every robot's coverage and sightings"
    )
    args = parser.parse_args(argv)
    try:
        candidates = reference_candidates(args.reference)
    except MrclamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.explain:
        for c in candidates:
            print(
                f"# {c.robot}: ground truth {c.ground_truth_s:.1f} s of the run, {c.sightings} sightings",
                file=sys.stderr,
            )
    print(candidates[0].robot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
