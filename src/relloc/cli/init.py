"""``relloc init BAG``: draft a team config (TOML, with comments) from what a bag holds.

Robots are the motion-capture bodies that have an odometry topic with the same number in its
name (``turtlebot1_cap`` and ``/cali/turtle01/odom``: robot ``turtle01``), or, in a bag without
odometry, every body (robot named after the body). Which UWB node is on which robot comes from
:func:`relloc.sources.inspect_bag.assign_nodes` (ranges against mocap distances); ``--node
ROBOT=NODE`` pins a robot's node. The reference is the robot whose node takes part in the most
range messages (ties by name); the area is the mocap extent plus :data:`MARGIN_M`, outward to
half metres. The file is never overwritten without ``--force``.

Exit status: 0 when the mapping is decided; 2 when it is not (the file is still written, the
mapping marked undecided in a comment: rerun with ``--node``), and for user errors (bag not
readable, file exists, bad ``--node``).
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomlkit

from relloc.cli.common import UserError
from relloc.sources.inspect_bag import (
    Assignment,
    BagInventory,
    assign_nodes,
    inspect_bag,
    robot_number,
)

MARGIN_M = 1.0
"""Margin added around the mocap extent for ``area`` (m)."""
TIE_M = 0.02
"""Two assignments whose scores differ by less than this (m, RMS) are a tie."""


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
    notes: list[str]
    """Lines for the summary and the file's comments (what was decided, how sure)."""
    seconds: float


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
        topic = next((t for t in by_number.get(n if n is not None else -1, []) if _same_kind(body, _odom_robot(t))), "")
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
            raise UserError(f"--node {item!r}: expected ROBOT=NODE with ROBOT one of {[r.name for r in robots]}")
        if node not in nodes:
            raise UserError(f"--node {item!r}: node {node!r} has no ranges in the bag; nodes: {nodes}")
        fixed[robot.body] = node
    return fixed


def draft(bag: Path, node_args: list[str]) -> tuple[BagInventory, Draft]:
    """Inspect the bag and decide robots, node mapping, reference and area."""
    inv = inspect_bag(bag)
    if len(inv.tracks) < 2:
        raise UserError(f"{bag}: fewer than two motion-capture bodies (/vrpn_client_node/<body>/pose): cannot draft a team")
    robots, notes = _robots(inv)
    if len(robots) < 2:
        raise UserError(f"{bag}: fewer than two robots found: {[r.name for r in robots]}")
    fixed = _parse_nodes(node_args, robots, inv.nodes)
    start = time.perf_counter()
    ranked = assign_nodes(inv, [r.body for r in robots], fixed=fixed, keep=2) if inv.ranges else []
    seconds = time.perf_counter() - start
    decided = False
    if ranked:
        best = ranked[0]
        for r in robots:
            r.node = best.nodes[r.body]
        if len(ranked) == 1:
            decided = True
            notes.append(f"node mapping: the only assignment with ranges for every pair, residual {best.rms:.3f} m")
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
            notes.append(f"  pinned by --node: {', '.join(sorted(f'{r.name}={fixed[r.body]}' for r in robots if r.body in fixed))}")
        extra = sorted(set(inv.nodes) - set(best.nodes.values()))
        if extra:
            notes.append(f"UWB nodes left out (on no robot, or a second tag): {', '.join(extra)}")
    else:
        notes.append("no UWB node mapping: no assignment has ranges between every pair of robots")
    counts = {r.name: inv.range_counts.get(r.node, 0) for r in robots}
    reference = min(counts, key=lambda n: (-counts[n], n))
    xs = [v for r in robots for v in inv.tracks[r.body][:, 1]]
    ys = [v for r in robots for v in inv.tracks[r.body][:, 2]]
    area = (
        math.floor((min(xs) - MARGIN_M) * 2) / 2,
        math.ceil((max(xs) + MARGIN_M) * 2) / 2,
        math.floor((min(ys) - MARGIN_M) * 2) / 2,
        math.ceil((max(ys) + MARGIN_M) * 2) / 2,
    )
    return inv, Draft(robots, reference, area, ranked, decided, notes, seconds)


def _distro(layout: str) -> str:
    return "humble" if layout == "humble" else "jazzy"


def to_toml(inv: BagInventory, d: Draft, name: str) -> str:
    """The drafted config as TOML text with comments."""
    doc = tomlkit.document()
    doc.add(tomlkit.comment(f"Drafted by relloc init from {inv.path}; check every value before trusting it."))
    for line in d.notes:
        doc.add(tomlkit.comment(line))
    doc.add("name", name)
    doc.add(tomlkit.comment("reference: the robot whose UWB node takes part in the most range messages (ties by name)"))
    doc.add("reference", d.reference)
    doc.add(tomlkit.comment(f"area: the robots' mocap extent plus {MARGIN_M:g} m, outward to half metres"))
    doc.add("area", [float(v) for v in d.area])
    layout = inv.range_layout or "unknown"
    doc.add(tomlkit.comment(f"ros_distro: the range messages have the {layout} layout of {inv.range_type or 'Range'}"))
    doc.add("ros_distro", _distro(inv.range_layout))
    quirks = _quirks(inv)
    if quirks:
        doc.add(tomlkit.nl())
        doc.add(tomlkit.comment("Clock quirks seen in the bag:"))
        for q in quirks:
            doc.add(tomlkit.comment(f"  {q}"))
    robots = tomlkit.aot()
    for r in d.robots:
        t = tomlkit.table()
        t.add("name", r.name)
        if r.node:
            t.add("uwb_node", r.node)
            if not d.decided:
                t["uwb_node"].comment("UNDECIDED: give it with --node")
        if r.odom:
            info = inv.odometry[r.odom]
            t.add("odom_topic", r.odom)
            if info.frozen_orientation:
                t.add("odom_mode", "twist")
                t["odom_mode"].comment("the orientation never changes: integrate the twist")
            if info.zero_stamps:
                flag = tomlkit.item(True)
                flag.comment("all header stamps are zero")
                t.add("odom_zero_stamps", flag)
        t.add("mocap_body", r.body)
        robots.append(t)
    doc.add("robots", robots)
    uwb = tomlkit.table()
    uwb.add("range_topic", inv.range_pattern or "/uwb/tof/{a}/{b}/distance")
    if inv.range_type and inv.range_type != "sensor_msgs/msg/Range":
        uwb.add("range_type", inv.range_type)
    doc.add(tomlkit.nl())
    doc.add(tomlkit.comment("Pair biases are not calibrated here: relloc calibrate BAG --config THIS.toml"))
    doc.add("uwb", uwb)
    return tomlkit.dumps(doc)


def _quirks(inv: BagInventory) -> list[str]:
    out = []
    if inv.far_stamps:
        offsets = sorted({round(v) for v in inv.far_stamps.values()})
        shown = ", ".join(f"{v:.0f}" for v in offsets[:3]) + (" ..." if len(offsets) > 3 else "")
        out.append(f"{len(inv.far_stamps)} topics stamp far from receive time (stamp - receive: {shown} s)")
    if inv.zero_stamp_topics:
        out.append(f"all-zero header stamps: {', '.join(inv.zero_stamp_topics)}")
    if inv.stale_ranges:
        out.append(f"{inv.stale_ranges} of {inv.range_messages} range messages repeat their topic's previous value")
    return out


def _cmd_init(args: argparse.Namespace) -> int:
    from relloc.config import TeamConfig
    from relloc.sources.rosbag import BagError, recording_name

    bag = Path(args.bag)
    out = Path(args.out) if args.out else Path(f"{recording_name(bag)}.toml")
    if out.exists() and not args.force:
        raise UserError(f"{out} exists; --force overwrites it")
    try:
        inv, d = draft(bag, args.node or [])
    except BagError as exc:
        raise UserError(str(exc)) from None
    text = to_toml(inv, d, recording_name(bag))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    TeamConfig.load(out)  # the draft must load; a failure here is a bug
    print(f"relloc init: {bag} -> {out}")
    for r in d.robots:
        extra = f", odometry {r.odom}" if r.odom else ""
        print(f"  {r.name}: mocap {r.body}, UWB {r.node or '-'}{extra}")
    print(f"  reference {d.reference}, area {list(d.area)}, ros_distro {_distro(inv.range_layout)}")
    for line in [*d.notes, *_quirks(inv)]:
        print(f"  {line}")
    print(f"  assignment search: {d.seconds:.2f} s")
    if not d.decided:
        print(f"relloc init: the node mapping is undecided; {out} is written with a guess. "
              "Rerun with --node ROBOT=NODE --force", file=sys.stderr)
        return 2
    return 0


def register(sub: Any) -> None:
    """Add ``init`` to the subcommands."""
    p = sub.add_parser(
        "init",
        help="draft a team config (TOML) from a bag: robots, UWB nodes, reference, area",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    p.add_argument("bag", help="rosbag2 folder (or .db3/.mcap file)")
    p.add_argument("--out", type=Path, default=None, help="the config to write (default: <recording>.toml)")
    p.add_argument("--force", action="store_true", help="overwrite an existing file")
    p.add_argument(
        "--node", action="append", metavar="ROBOT=NODE",
        help="pin a robot's UWB node (repeatable), e.g. turtle01=n_2",
    )
    p.set_defaults(handler=_cmd_init)


