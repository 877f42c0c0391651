"""What a rosbag2 bag holds, for drafting a team config (``relloc init``).

:func:`inspect_bag` reads a bag once: topics and types, motion-capture bodies
(:func:`mocap_patterns`), odometry topics with messages, the UWB range topic pattern
and its node ids, the range type's layout (Humble or later) and clock quirks (header stamps far
from receive time, zero stamps, stale repeated ranges). :func:`assign_nodes` finds which UWB node
is on which body: for every assignment (a depth-first search with pruning on a non-negative
additive cost) each pair's ranges are compared with the mocap distances at the same times.
A pair's cost is the mean clipped squared residual around its own bias, the bias held to
``[BIAS_MIN, BIAS_MAX]`` (UWB ranges read long by up to about 1 m, never metres): a wrong node
pair of a moving team leaves a spread of metres, and one of a static team a bias outside that
window. Pure functions of the bag; nothing here knows about the command line.

Motion capture is found by message type, whatever the naming. A topic of one of
:data:`~relloc.ros.messages.MOCAP_TYPES` (``PoseStamped``, ``PoseWithCovarianceStamped``,
``TransformStamped``, ``Odometry``) may carry a body's pose, except a robot's own odometry: an
``Odometry`` topic with ``odom`` in a name part and no motion-capture word (:data:`MOCAP_WORDS`)
in any (``/tb1/odom``, ``/cali/turtle01/odom``). Each other such topic gives one pattern per name
part, that part replaced by ``{body}`` (``/tb1/world`` -> ``/{body}/world``, ``/tb1/{body}``).
The pattern chosen is, among those matching at least two topics of one type, the one with a
motion-capture word outside ``{body}`` (``/vrpn_client_node/{body}/pose``, ``/mocap/{body}/pose``,
``/{body}/world``), then the most bodies, then the shortest and first by name; the runners-up
(each sharing no topic with a better one: ``/tb1/{body}`` is another reading of ``/tb1/world``)
are kept (:attr:`BagInventory.mocap_others`) so that a caller can say the choice was close. A
given pattern (``relloc init --mocap-topic``) replaces the search: every topic of a motion-capture
type it matches is a body, an ``Odometry`` one included.
"""

from __future__ import annotations

import math
import re
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np

from relloc.events import pair_key
from relloc.ros.distros import layout_of_definition, layouts
from relloc.ros.messages import (
    MOCAP_TYPES,
    ODOMETRY,
    MessageDecodeError,
    decode,
    pose_to_ground_truth,
    stamp_to_sec,
)
from relloc.sources.rosbag import _open_reader
from relloc.sources.tracks import interpolate_track

__all__ = [
    "Assignment",
    "BagInventory",
    "MocapPattern",
    "assign_nodes",
    "inspect_bag",
    "mocap_patterns",
    "mocap_regex",
    "robot_number",
    "robot_odometry",
]

MOCAP_WORDS = (
    "vrpn",
    "mocap",
    "motion_capture",
    "optitrack",
    "vicon",
    "qualisys",
    "natnet",
    "world",
)
"""Name parts holding one of these mark a motion-capture topic (and an ``Odometry`` one as not a
robot's own odometry)."""
RANGE_RE = re.compile(r"^(?P<pre>/.*?)(?P<a>n_?\w+)/(?P<b>n_?\w+)(?P<post>/distance)$")
BIAS_MIN = -0.2
"""Lowest plausible pair bias (m): a range shorter than the true distance by more is wrong."""
BIAS_MAX = 1.0
"""Highest plausible pair bias (m)."""
CLIP = 1.0
"""Residuals are clipped at this (m): NLOS spikes must not decide the assignment."""
FAR_STAMP_S = 1.0
"""A topic whose header stamps differ from receive time by more than this is reported (s)."""
MAX_SAMPLES = 2000
"""At most this many ranges per pair enter the assignment (evenly thinned)."""


@dataclass
class OdomInfo:
    """One odometry topic: its messages, whether all stamps are zero and the orientation frozen."""

    topic: str
    count: int
    zero_stamps: bool
    frozen_orientation: bool


@dataclass(frozen=True)
class MocapPattern:
    """A motion-capture topic pattern (with ``{body}``), its message type and its topics."""

    pattern: str
    msgtype: str
    topics: dict[str, str]
    """Topic -> body."""

    @property
    def hinted(self) -> bool:
        """Whether a name part outside ``{body}`` holds a :data:`MOCAP_WORDS` word."""
        return _has_mocap_word(self.pattern.replace("{body}", ""))


def _has_mocap_word(topic: str) -> bool:
    return any(w in part.lower() for part in topic.split("/") for w in MOCAP_WORDS)


def robot_odometry(topic: str, msgtype: str) -> bool:
    """Whether ``topic`` is a robot's own odometry, never motion capture (module docstring)."""
    parts = [p.lower() for p in topic.split("/") if p]
    return msgtype == ODOMETRY and any("odom" in p for p in parts) and not _has_mocap_word(topic)


def mocap_regex(pattern: str) -> re.Pattern[str]:
    """The regular expression of a pattern with ``{body}`` (one name part or a piece of one)."""
    if "{body}" not in pattern:
        raise ValueError(f"motion-capture pattern {pattern!r} has no {{body}}")
    head, _, tail = pattern.partition("{body}")
    return re.compile(f"^{re.escape(head)}(?P<body>[^/]+){re.escape(tail)}$")


def mocap_patterns(topics: Mapping[str, str], pattern: str | None = None) -> list[MocapPattern]:
    """The motion-capture patterns of ``topics`` (topic -> type), best first (module
    docstring); with ``pattern`` given, just that one (empty when it matches no topic of a
    motion-capture type)."""
    if pattern is not None:
        regex = mocap_regex(pattern)
        by_type: dict[str, dict[str, str]] = defaultdict(dict)
        for topic, msgtype in sorted(topics.items()):
            if msgtype in MOCAP_TYPES and (m := regex.match(topic)):
                by_type[msgtype][topic] = m["body"]
        return sorted(
            (MocapPattern(pattern, t, found) for t, found in by_type.items()),
            key=lambda p: (-len(p.topics), p.msgtype),
        )[:1]
    found: dict[tuple[str, str], dict[str, str]] = defaultdict(dict)
    for topic, msgtype in sorted(topics.items()):
        if msgtype not in MOCAP_TYPES or robot_odometry(topic, msgtype):
            continue
        parts = topic.split("/")
        for i, part in enumerate(parts):
            if part:
                key = ("/".join([*parts[:i], "{body}", *parts[i + 1 :]]), msgtype)
                found[key][topic] = part
    ranked = sorted(
        (MocapPattern(p, t, bodies) for (p, t), bodies in found.items() if len(bodies) >= 2),
        key=lambda p: (not p.hinted, -len(p.topics), len(p.pattern), p.pattern),
    )
    out: list[MocapPattern] = []
    for candidate in ranked:  # another reading of a better pattern's topics is none
        if not any(set(candidate.topics) & set(better.topics) for better in out):
            out.append(candidate)
    return out


@dataclass
class BagInventory:
    """What :func:`inspect_bag` found in a bag."""

    path: Path
    topics: dict[str, str]
    """Topic -> message type, topics with messages only."""
    tracks: dict[str, np.ndarray]
    """Mocap body -> ``(n, 3)`` rows ``t, x, y`` (header time, else receive time)."""
    odometry: dict[str, OdomInfo]
    range_pattern: str
    range_type: str
    range_layout: str
    """``humble``, or the later distributions' layout name (``iron..rolling``); empty: unknown."""
    ranges: dict[str, np.ndarray]
    """Node pair key -> ``(n, 2)`` rows ``t, range`` (both directions merged)."""
    range_counts: dict[str, int]
    """Node -> range messages it takes part in."""
    far_stamps: dict[str, float] = field(default_factory=dict)
    """Topic -> median header stamp minus receive time (s), where beyond :data:`FAR_STAMP_S`."""
    zero_stamp_topics: list[str] = field(default_factory=list)
    stale_ranges: int = 0
    """Range messages repeating their topic's previous value."""
    range_messages: int = 0
    mocap_pattern: str = ""
    """The motion-capture topic pattern (with ``{body}``) the tracks come from; empty: none."""
    mocap_type: str = ""
    mocap_others: list[str] = field(default_factory=list)
    """Runner-up motion-capture patterns as ``pattern (type, n bodies)`` (:func:`mocap_patterns`)."""

    @property
    def nodes(self) -> list[str]:
        return sorted(self.range_counts)


def robot_number(name: str) -> int | None:
    """The number in a robot or body name (``turtlebot1_cap`` -> 1, ``turtle01`` -> 1)."""
    m = re.search(r"(\d+)", name)
    return int(m.group(1)) if m else None


def _range_topics(topics: Mapping[str, str]) -> tuple[str, dict[str, tuple[str, str]]]:
    """The range topic pattern (``{a}``/``{b}`` for node ids) and each range topic's nodes."""
    found: dict[str, tuple[str, str]] = {}
    patterns: dict[str, int] = defaultdict(int)
    for topic, msgtype in topics.items():
        m = RANGE_RE.match(topic)
        if m and msgtype.endswith("/Range"):
            patterns[f"{m['pre']}{{a}}/{{b}}{m['post']}"] += 1
            found[topic] = (m["a"], m["b"])
    if not found:
        return "", {}
    pattern = max(patterns, key=lambda p: patterns[p])
    return pattern, found


def inspect_bag(path: str | Path, mocap_topic: str | None = None) -> BagInventory:
    """Read a bag once and list what a team config needs (see the module docstring);
    ``mocap_topic`` (a pattern with ``{body}``) says where motion capture is, else it is found.

    Raises :class:`~relloc.sources.rosbag.BagError` when the bag cannot be opened.
    """
    path = Path(path)
    with _open_reader(path) as reader:
        conns = [c for c in reader.connections if c.msgcount > 0]
        topics = {c.topic: c.msgtype for c in conns}
        pattern, range_nodes = _range_topics(topics)
        range_type, layout = "", ""
        for c in conns:
            if c.topic in range_nodes and c.msgdef is not None and not layout:
                range_type = c.msgtype
                lay = layout_of_definition(c.msgtype, c.msgdef.data)
                layout = lay.name if lay is not None else ""
        patterns = mocap_patterns(topics, mocap_topic)
        mocap = dict(patterns[0].topics) if patterns else {}
        odom_topics = [t for t, ty in topics.items() if ty == ODOMETRY and t not in mocap]
        wanted = [
            c for c in conns if c.topic in range_nodes or c.topic in mocap or c.topic in odom_topics
        ]
        rows: dict[str, list[tuple[float, float, float]]] = defaultdict(list)
        stamp_minus_recv: dict[str, list[float]] = defaultdict(list)
        zero: dict[str, bool] = defaultdict(lambda: True)
        quats: dict[str, set[tuple[float, ...]]] = defaultdict(set)
        last_value: dict[str, float] = {}
        stale = 0
        for conn, recv_ns, raw in reader.messages(wanted) if wanted else ():
            try:
                msg = decode(raw, conn.msgtype)
            except MessageDecodeError:
                continue
            recv = recv_ns * 1e-9
            stamp = stamp_to_sec(msg.header.stamp)
            topic = conn.topic
            if stamp != 0.0:
                zero[topic] = False
                if len(stamp_minus_recv[topic]) < 200:
                    stamp_minus_recv[topic].append(stamp - recv)
            else:
                zero[topic] &= True  # stays True only while every stamp is zero
            t = stamp if stamp != 0.0 else recv
            if topic in mocap:
                gt = pose_to_ground_truth(msg, "", t=t)
                rows[topic].append((t, gt.position[0], gt.position[1]))
            elif topic in range_nodes:
                if not layout:  # no stored definition: the layout the payload fits
                    layout = next(
                        (
                            lay.name
                            for lay in layouts(conn.msgtype)
                            if _fits(raw, conn.msgtype, lay)
                        ),
                        "",
                    )
                value = float(msg.range)
                if last_value.get(topic) == value:
                    stale += 1
                last_value[topic] = value
                if math.isfinite(value) and value > 0.0:
                    rows[topic].append((t, value, 0.0))
                else:
                    rows[topic].append((t, math.nan, 0.0))
            else:
                q = msg.pose.pose.orientation
                quats[topic].add((q.x, q.y, q.z, q.w))
                rows[topic].append((t, 0.0, 0.0))
    tracks = {}
    for topic, body in mocap.items():
        arr = np.array(rows[topic], dtype=float).reshape(-1, 3)
        tracks[body] = arr[np.argsort(arr[:, 0], kind="stable")]
    odometry = {
        t: OdomInfo(t, len(rows[t]), zero[t], len(rows[t]) > 1 and len(quats[t]) == 1)
        for t in odom_topics
    }
    ranges: dict[str, list[tuple[float, float]]] = defaultdict(list)
    counts: dict[str, int] = defaultdict(int)
    for topic, (a, b) in range_nodes.items():
        key = pair_key(a, b)
        got = [(t, r) for t, r, _ in rows[topic] if math.isfinite(r)]
        ranges[key].extend(got)
        counts[a] += len(rows[topic])
        counts[b] += len(rows[topic])
    range_arrays = {}
    for key, v in ranges.items():
        arr = np.array(v, dtype=float).reshape(-1, 2)
        range_arrays[key] = arr[np.argsort(arr[:, 0], kind="stable")]
    far = {
        t: round(float(np.median(v)), 3)
        for t, v in stamp_minus_recv.items()
        if v and abs(float(np.median(v))) > FAR_STAMP_S
    }
    return BagInventory(
        path=path,
        topics=topics,
        tracks=tracks,
        odometry=odometry,
        range_pattern=pattern,
        range_type=range_type,
        range_layout=layout,
        ranges=range_arrays,
        range_counts=dict(counts),
        far_stamps=far,
        zero_stamp_topics=sorted(t for t in rows if zero[t]),
        stale_ranges=stale,
        range_messages=sum(len(rows[t]) for t in range_nodes),
        mocap_pattern=patterns[0].pattern if patterns else "",
        mocap_type=patterns[0].msgtype if patterns else "",
        mocap_others=[f"{p.pattern} ({p.msgtype}, {len(p.topics)} bodies)" for p in patterns[1:]],
    )


def _fits(raw: bytes | memoryview, msgtype: str, layout: Any) -> bool:
    try:
        decode(raw, msgtype, layout)
    except MessageDecodeError:
        return False
    return True


@dataclass(frozen=True)
class Assignment:
    """One mapping body -> node and its score (RMS of the clipped residuals, m)."""

    nodes: dict[str, str]
    rms: float
    pair_bias: dict[str, float]
    """Node pair key -> median(range - mocap distance) (m)."""


def _pair_cost(
    rng: np.ndarray, a: np.ndarray, b: np.ndarray, max_gap: float
) -> tuple[float, float] | None:
    """(cost, median bias) of one node pair on one body pair, or ``None`` without matched times."""
    if rng.shape[0] > MAX_SAMPLES:
        rng = rng[np.linspace(0, rng.shape[0] - 1, MAX_SAMPLES).astype(int)]
    t = rng[:, 0]
    xa, ya, va = interpolate_track(a[:, 0], a[:, 1], a[:, 2], t, max_gap=max_gap)
    xb, yb, vb = interpolate_track(b[:, 0], b[:, 1], b[:, 2], t, max_gap=max_gap)
    ok = va & vb
    if not ok.any():
        return None
    e = rng[ok, 1] - np.hypot(xa - xb, ya - yb)[ok]
    median = float(np.median(e))
    bias = min(max(median, BIAS_MIN), BIAS_MAX)
    return float(np.mean(np.minimum((e - bias) ** 2, CLIP**2))), median


def assign_nodes(
    inv: BagInventory,
    bodies: Sequence[str],
    *,
    fixed: Mapping[str, str] | None = None,
    max_gap: float = 0.1,
    keep: int = 2,
) -> list[Assignment]:
    """The ``keep`` best injective maps body -> node whose every pair has ranges, best first.

    ``fixed`` pins some bodies to nodes. The total cost is the sum of the pairs' costs, so a
    depth-first search prunes every branch whose partial sum already exceeds the ``keep``-th best
    complete one. An empty list: no assignment has ranges for all its pairs.
    """
    fixed = dict(fixed or {})
    nodes = inv.nodes
    cost: dict[tuple[str, str, str], tuple[float, float]] = {}
    for ba, bb in combinations(bodies, 2):
        for key, rng in inv.ranges.items():
            got = _pair_cost(rng, inv.tracks[ba], inv.tracks[bb], max_gap)
            if got is not None:
                cost[(ba, bb, key)] = got
    order = sorted(bodies, key=lambda b: (b not in fixed, bodies.index(b)))
    npairs = len(bodies) * (len(bodies) - 1) // 2
    best: list[tuple[float, dict[str, str]]] = []

    def bound() -> float:
        return best[-1][0] if len(best) >= keep else math.inf

    def search(i: int, chosen: dict[str, str], total: float) -> None:
        if total > bound():
            return
        if i == len(order):
            best.append((total, dict(chosen)))
            best.sort(key=lambda x: (x[0], sorted(x[1].items())))
            del best[keep:]
            return
        body = order[i]
        candidates = [fixed[body]] if body in fixed else nodes
        used = set(chosen.values())
        for node in candidates:
            if node in used:
                continue
            add = 0.0
            for other, onode in chosen.items():
                ba, bb = (
                    (other, body) if bodies.index(other) < bodies.index(body) else (body, other)
                )
                c = cost.get((ba, bb, pair_key(node, onode)))
                if c is None:
                    break
                add += c[0]
            else:
                chosen[body] = node
                search(i + 1, chosen, total + add)
                del chosen[body]

    search(0, {}, 0.0)
    out = []
    for total, mapping in best:
        biases = {}
        for ba, bb in combinations(bodies, 2):
            key = pair_key(mapping[ba], mapping[bb])
            biases[key] = round(cost[(ba, bb, key)][1], 3)
        out.append(
            Assignment(
                {b: mapping[b] for b in bodies}, round(math.sqrt(total / max(npairs, 1)), 4), biases
            )
        )
    return out
