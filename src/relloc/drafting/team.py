"""A team config drafted from what a bag holds: robots, node mapping, reference, area.

Robots are the motion-capture bodies that have an odometry topic with the same number in its
name (``turtlebot1_cap`` and ``/cali/turtle01/odom``: robot ``turtle01``), or, in a bag without
odometry, every body (robot named after the body). Motion capture is found by message type,
whatever the topic naming (:mod:`relloc.sources.inspect_bag`: a ``PoseStamped``,
``PoseWithCovarianceStamped``, ``TransformStamped`` or ``Odometry`` topic pattern with ``{body}``
in one name part, not a robot's own odometry), or given as a pattern (``mocap_topic``); the
draft carries the pattern as the config's ``mocap_topic``. Which UWB node is on which robot
comes from :func:`relloc.sources.inspect_bag.assign_nodes` (ranges against mocap distances);
``node_args`` (``ROBOT=NODE``) pin a robot's node. A node left over that moves with one body is a
second tag on it (:func:`relloc.drafting.tags.find_tags`: the body, and the tag's lever arm by
least squares against the body's mocap poses; in 3D when the bodies fly,
:data:`FLYING_SPREAD_M`). Ranges of a driver's node frames are read by
:mod:`relloc.drafting.frames`. The reference is the robot whose node takes
part in the most range messages (ties by name; ``reference`` picks another). The area is the
project's default prior box (:class:`~relloc.config.TeamConfig` ``area``) centred on the
robots' mocap extent, or that extent plus :data:`MARGIN_M` where it is larger: a short
recording's extent understates where the team may be, and the filter uses only the box's size.

With the mapping decided, :func:`calibrate_draft` estimates what ``relloc calibrate BAG
--headings`` does from the same bag's motion capture (:func:`relloc.drafting.calibrate.calibrate`):
the node-pair biases and each robot's ``heading_offset_deg``.
"""

from __future__ import annotations

import math
import re
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from relloc.config import TeamConfig
from relloc.drafting.calibrate import Calibration, calibrate
from relloc.drafting.delay import range_delay, shifted
from relloc.drafting.frames import with_node_frames
from relloc.drafting.tags import Poses, TagFit, find_tags, mocap_poses
from relloc.ros.messages import MOCAP_TYPES
from relloc.sources.inspect_bag import (
    Assignment,
    BagInventory,
    assign_nodes,
    inspect_bag,
    robot_number,
)

__all__ = ["Draft", "DraftError", "Robot", "calibrate_draft", "draft"]


class DraftError(ValueError):
    """The bag cannot give a team config as asked (too few bodies, a bad pinned node)."""


MARGIN_M = 1.0
"""Margin added around the mocap extent for ``area`` where the default box is too small (m)."""
DEFAULT_AREA: tuple[float, float, float, float] = TeamConfig.area
"""The project's default prior box; its size is the least a drafted ``area`` gets."""
REFERENCE_TIE = 0.05
"""Range counts within this fraction of the most are called a near tie in the reference note."""
TIE_M = 0.02
"""Two assignments whose scores differ by less than this (m, RMS) are a tie."""
FLYING_SPREAD_M = 0.5
"""The team flies (``dimension = 3``) when its bodies' mocap heights, all samples together,
spread over more than this (m, 2nd to 98th percentile): bodies at different heights or one
climbing. A ground team's markers sit within a few decimetres of one another, and below this a
planar range model errs by at most ``h**2 / (2 d)``: 6 cm at 2 m, under the UWB noise."""


@dataclass
class Robot:
    """One drafted robot."""

    name: str
    body: str
    odom: str = ""
    node: str = ""


@dataclass
class Draft:
    """The drafted team and what was decided."""

    robots: list[Robot]
    reference: str
    area: tuple[float, float, float, float]
    ranked: list[Assignment]
    decided: bool
    reference_note: str
    """How the reference was chosen and how clearly (the runner-up's range count)."""
    notes: list[str]
    """Lines for the summary and the file's comments (what was decided, how sure)."""
    seconds: float
    tags: list[TagFit] = field(default_factory=list)
    """Second tags: nodes the mapping leaves out that move with one body
    (:func:`relloc.drafting.tags.find_tags`), with their lever arms (in 3D, the first tags of
    their bodies too, marked ``first``)."""
    dimension: int = 2
    height_spread: float = 0.0
    """Spread of the bodies' mocap heights (m; :data:`FLYING_SPREAD_M`)."""
    range_delay: float = 0.0
    """How long the range stamps lag the geometry (s; :func:`relloc.drafting.delay.range_delay`,
    measured for a flying team only: a ground team's estimators read the stamps)."""

    def tags_of(self, robot: Robot) -> list[TagFit]:
        """The extra tags on ``robot`` (its first is :attr:`Robot.node`)."""
        return [t for t in self.tags if t.body == robot.body and not t.first]

    def first_fit(self, robot: Robot) -> TagFit | None:
        """Where ``robot``'s first tag sits, where it was placed from the mocap origin (3D)."""
        return next((t for t in self.tags if t.body == robot.body and t.first), None)


def height_spread(poses: Poses) -> float:
    """Spread (m) of every body's mocap heights together: 2nd to 98th percentile, so that a few
    wild samples do not make a ground team fly."""
    z = np.concatenate([p[:, 3] for p in poses.values()] or [np.zeros(1)])
    lo, hi = np.percentile(z, [2.0, 98.0]) if z.size else (0.0, 0.0)
    return float(hi - lo)


def _odom_robot(topic: str) -> str:
    """The namespace of an odometry topic that names the robot (``/cali/turtle01/odom`` -> turtle01)."""
    parts = [p for p in topic.split("/") if p]
    named = [p for p in parts if robot_number(p) is not None]
    return named[-1] if named else (parts[-2] if len(parts) > 1 else parts[0])


def _same_kind(body: str, robot: str) -> bool:
    """Whether a body and a robot name start alike (``turtlebot1_cap``, ``turtle01``; not ``chair2``)."""
    stem_a, stem_b = (re.match(r"[a-z]*", s.lower()).group(0) for s in (body, robot))  # type: ignore[union-attr]
    return not stem_a or not stem_b or stem_a[:3] == stem_b[:3]


def _robots(inv: BagInventory) -> tuple[list[Robot], list[str]]:
    """Robots from mocap bodies and odometry topics, and notes on what was left out."""
    notes: list[str] = []
    by_number: dict[int, list[str]] = {}
    for topic, _info in sorted(inv.odometry.items(), key=lambda kv: (-kv[1].count, kv[0])):
        n = robot_number(_odom_robot(topic))
        if n is not None:
            by_number.setdefault(n, []).append(topic)
    robots = []
    for body in sorted(inv.tracks):
        n = robot_number(body)
        topic = next(
            (
                t
                for t in by_number.get(n if n is not None else -1, [])
                if _same_kind(body, _odom_robot(t))
            ),
            "",
        )
        if topic:
            robots.append(Robot(_odom_robot(topic), body, odom=topic))
    if not robots:
        robots = [Robot(body, body) for body in sorted(inv.tracks)]
    else:
        others = sorted(set(inv.tracks) - {r.body for r in robots})
        if others:
            notes.append(f"mocap bodies without odometry, not robots: {', '.join(others)}")
        used = {r.odom for r in robots}
        spare = sorted(t for t in inv.odometry if t not in used)
        if spare:
            notes.append(f"odometry topics of no mocap body, left out: {', '.join(spare)}")
    return robots, notes


def _parse_nodes(items: list[str], robots: list[Robot], nodes: list[str]) -> dict[str, str]:
    """``--node ROBOT=NODE`` (robot or body name) -> body -> node."""
    fixed: dict[str, str] = {}
    for item in items:
        name, _, node = item.partition("=")
        robot = next((r for r in robots if name in (r.name, r.body)), None)
        if robot is None or not node:
            raise DraftError(
                f"--node {item!r}: expected ROBOT=NODE with ROBOT one of {[r.name for r in robots]}"
            )
        if node not in nodes:
            raise DraftError(
                f"--node {item!r}: node {node!r} has no ranges in the bag; nodes: {nodes}"
            )
        fixed[robot.body] = node
    return fixed


def _axis(lo: float, hi: float, default: float) -> tuple[float, float]:
    """One axis of ``area``: the default width centred on ``lo..hi`` (centre to half metres), or
    ``lo..hi`` plus :data:`MARGIN_M` outward to half metres where that is wider."""
    if hi - lo + 2 * MARGIN_M > default:
        return math.floor((lo - MARGIN_M) * 2) / 2, math.ceil((hi + MARGIN_M) * 2) / 2
    centre = round((lo + hi) / 2 * 2) / 2
    return centre - default / 2, centre + default / 2


def _reference(robots: list[Robot], counts: dict[str, int], pinned: str | None) -> tuple[str, str]:
    """The reference robot and a note saying how it was chosen."""
    if pinned is not None:
        if pinned not in counts:
            raise DraftError(f"--reference {pinned!r}: expected one of {[r.name for r in robots]}")
        return pinned, f"reference: {pinned}, given by --reference"
    ranked = sorted(counts, key=lambda n: (-counts[n], n))
    best, second = ranked[0], ranked[1]
    share = (counts[best] - counts[second]) / max(counts[best], 1)
    how = (
        "a near tie, so the choice is arbitrary; --reference picks another"
        if share < REFERENCE_TIE
        else "clearly"
    )
    return best, (
        f"reference: {best}, its node in the most range messages ({counts[best]}; "
        f"{second} {counts[second]}): {how}"
    )


def _no_mocap(bag: Path, inv: BagInventory, mocap_topic: str | None) -> DraftError:
    """The error for a bag with fewer than two motion-capture bodies: what was looked for."""
    types = ", ".join(t.rpartition("/")[2] for t in MOCAP_TYPES)
    found = (
        f" (found: {', '.join(sorted(inv.tracks))} on {inv.mocap_pattern})" if inv.tracks else ""
    )
    if mocap_topic is not None:
        return DraftError(
            f"{bag}: fewer than two motion-capture bodies on {mocap_topic!r} (topics of type "
            f"{types}){found}: cannot draft a team"
        )
    return DraftError(
        f"{bag}: fewer than two motion-capture bodies{found}: looked for topics of type {types} "
        "(not a robot's odometry) sharing a name pattern with one part the body; give the "
        "pattern with --mocap-topic, e.g. --mocap-topic '/{body}/world'"
    )


def draft(
    bag: Path,
    node_args: list[str],
    reference: str | None = None,
    mocap_topic: str | None = None,
) -> tuple[BagInventory, Draft]:
    """Inspect the bag and decide robots, node mapping, reference and area; ``mocap_topic``
    (a pattern with ``{body}``) says where motion capture is, else it is found by type."""
    try:
        inv = inspect_bag(bag, mocap_topic)
    except ValueError as exc:  # a pattern without {body}
        if isinstance(exc, DraftError) or "{body}" not in str(exc):
            raise
        raise DraftError(f"--mocap-topic: {exc}") from None
    if len(inv.tracks) < 2:
        raise _no_mocap(bag, inv, mocap_topic)
    inv = with_node_frames(bag, inv)
    robots, notes = _robots(inv)
    how = "given" if mocap_topic is not None else "found by type"
    notes.insert(0, f"motion capture: {inv.mocap_pattern} ({inv.mocap_type}, {how})")
    if inv.mocap_others:
        notes.insert(
            1,
            f"  other motion-capture patterns (--mocap-topic picks): {'; '.join(inv.mocap_others)}",
        )
    if len(robots) < 2:
        raise DraftError(f"{bag}: fewer than two robots found: {[r.name for r in robots]}")
    fixed = _parse_nodes(node_args, robots, inv.nodes)
    poses = mocap_poses(bag, inv, [r.body for r in robots])
    spread = height_spread(poses)
    dimension = 3 if spread > FLYING_SPREAD_M else 2
    if dimension == 3:
        notes.append(
            f"dimension 3: the bodies' mocap heights spread over {spread:.2f} m (more than "
            f"{FLYING_SPREAD_M:g} m: they fly)"
        )
    start = time.perf_counter()
    ranked = assign_nodes(inv, [r.body for r in robots], fixed=fixed, keep=2) if inv.ranges else []
    seconds = time.perf_counter() - start
    decided = False
    delay = 0.0
    tags: list[TagFit] = []
    if ranked:
        best = ranked[0]
        for r in robots:
            r.node = best.nodes[r.body]
        if len(ranked) == 1:
            decided = True
            notes.append(
                f"node mapping: the only assignment with ranges for every pair, residual {best.rms:.3f} m"
            )
        else:
            second = ranked[1]
            name = {r.body: r.name for r in robots}
            differ = sorted(b for b in best.nodes if best.nodes[b] != second.nodes[b])
            close = second.rms - best.rms < TIE_M
            same_nodes = set(best.nodes.values()) == set(second.nodes.values())
            if close and same_nodes and len(fixed) < len(robots):
                notes.append(
                    f"node mapping UNDECIDED: {best.rms:.3f} m vs {second.rms:.3f} m when "
                    f"{', '.join(name[b] for b in differ)} swap nodes (one symmetric pair cannot tell them apart); "
                    "give it with --node ROBOT=NODE"
                )
            else:
                decided = True
                notes.append(
                    f"node mapping: residual {best.rms:.3f} m, runner-up {second.rms:.3f} m "
                    f"({', '.join(f'{name[b]}={second.nodes[b]}' for b in differ)})"
                )
                if close:
                    alt = ", ".join(f"{second.nodes[b]} on {name[b]}" for b in differ)
                    notes.append(f"  {alt} fits as well: perhaps a second tag on the same robot")
        if fixed:
            notes.append(
                f"  pinned by --node: {', '.join(sorted(f'{r.name}={fixed[r.body]}' for r in robots if r.body in fixed))}"
            )
        if dimension == 3 and decided:
            delay, spread_at, spread_zero = range_delay(
                inv, poses, {n: b for b, n in best.nodes.items()}, dimension
            )
            if delay > 0.0:
                notes.append(
                    f"range delay: the ranges measure the mocap distances {delay:.2f} s before "
                    f"their stamps (spread about them {spread_at:.3f} m, {spread_zero:.3f} m at "
                    "the stamps): an averaging driver"
                )
                inv = shifted(inv, delay)
        extra = sorted(set(inv.nodes) - set(best.nodes.values()))
        if extra and decided:
            name = {r.body: r.name for r in robots}
            tags, tag_notes = find_tags(inv, poses, best.nodes, best.pair_bias, name, dimension)
            for t in (t for t in tags if not t.first):
                runner = (
                    f", next best {name[t.runner_up]} {t.runner_up_rms:.3f} m"
                    if t.runner_up
                    else "; no other body fits"
                )
                notes.append(
                    f"second tag: {t.node} on {name[t.body]} (moves with its mocap body: residual "
                    f"{t.rms:.3f} m over ranges to {t.partners} nodes{runner})"
                )
            notes += [f"  {line}" for line in tag_notes]
            extra = sorted(set(extra) - {t.node for t in tags})
        if extra:
            notes.append(f"UWB nodes left out (on no robot, or a second tag): {', '.join(extra)}")
    else:
        notes.append("no UWB node mapping: no assignment has ranges between every pair of robots")
    counts = {r.name: inv.range_counts.get(r.node, 0) for r in robots}
    chosen, reference_note = _reference(robots, counts, reference)
    xs = [v for r in robots for v in inv.tracks[r.body][:, 1]]
    ys = [v for r in robots for v in inv.tracks[r.body][:, 2]]
    dx0, dx1, dy0, dy1 = DEFAULT_AREA
    area = (*_axis(min(xs), max(xs), dx1 - dx0), *_axis(min(ys), max(ys), dy1 - dy0))
    return inv, Draft(
        robots,
        chosen,
        area,
        ranked,
        decided,
        reference_note,
        notes,
        seconds,
        tags,
        dimension,
        spread,
        delay,
    )


def calibrate_draft(bag: Path, text: str, d: Draft) -> tuple[Calibration | None, list[str]]:
    """What ``relloc calibrate --headings`` estimates, from this bag's motion capture, for the
    drafted config ``text``; ``None`` (and why) when the mapping is undecided or nothing matched.
    The notes say what was calibrated and how sure."""
    from relloc.evaluation.calibration import CalibrationError

    if not d.decided:
        return None, ["not calibrated: the node mapping is undecided (rerun with --node)"]
    config = TeamConfig.from_dict(tomllib.loads(text))
    try:
        cal = calibrate(
            bag,
            config,
            headings=any(r.odom for r in d.robots),
            bias_errors=config.dimension == 3,
        )
    except CalibrationError as exc:
        return None, [f"not calibrated: {exc}"]
    headings = {r: deg + 0.0 for r, deg in cal.heading_offset_deg.items()}  # no -0.0
    cal = Calibration(cal.source, cal.pairs, headings, cal.fit_scale, cal.range_sigma)
    notes = [
        "calibrated from this bag's motion capture (in-sample: a run of this bag with it scores "
        "against the truth it was fitted to; --no-calibrate leaves it out):"
    ]
    if cal.pairs:
        biases = [p.bias for p in cal.pairs.values()]
        sigmas = {k: p.sigma for k, p in cal.pairs.items() if p.sigma is not None}
        line = f"  {len(cal.pairs)} pair biases {min(biases):.3f}..{max(biases):.3f} m"
        if sigmas:
            widest = max(sigmas, key=lambda k: sigmas[k])
            line += (
                f", robust sigma of what is left {min(sigmas.values()):.3f}..{max(sigmas.values()):.3f} m "
                f"(widest {widest})"
            )
        notes.append(line)
        if cal.range_sigma is not None:
            notes.append(
                f"  range noise {cal.range_sigma:.3f} m (RMS of what the biases leave, outliers included): "
                "written as [uwb] sigma and los_sigma, what the flying team's smoother weighs "
                "every range by"
            )
        errors = [p.bias_sigma for p in cal.pairs.values() if p.bias_sigma is not None]
        if errors:
            notes.append(
                f"  each pair bias known to {min(errors):.3f}..{max(errors):.3f} m on this bag "
                "(standard error): written as bias_sigma, what the online biases start from"
            )
    if headings:
        shown = ", ".join(f"{r} {deg:+.2f}" for r, deg in headings.items())
        notes.append(
            f"  heading offsets (deg, mocap yaw - odometry yaw at the first odometry message, "
            f"one pose each: as sure as that mocap yaw): {shown}"
        )
    missing = [r.name for r in d.robots if r.odom and r.name not in headings]
    if missing:
        notes.append(
            f"  no heading offset (no mocap pose near the first odometry): {', '.join(missing)}"
        )
    return cal, notes
