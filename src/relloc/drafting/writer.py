"""The TOML text of a drafted team config (:mod:`relloc.drafting.team`), with comments: what was
decided and how sure, the clock quirks seen in the bag."""

from __future__ import annotations

import tomlkit
from tomlkit.items import Item

from relloc.config import TeamConfig
from relloc.drafting.tags import TagFit
from relloc.drafting.team import MARGIN_M, Draft, Robot
from relloc.sources.inspect_bag import BagInventory

__all__ = ["distro", "quirks", "to_toml"]


def distro(layout: str) -> str:
    return "humble" if layout == "humble" else "jazzy"


def _tags(r: Robot, fits: list[TagFit], lever_arms: bool) -> Item:
    """``tags = [...]`` of a robot with extra tags: its first node at the body origin, each
    extra one at its estimated lever arm (standard errors in the comment), or at the origin to be
    measured when ``lever_arms`` is false."""
    arr = tomlkit.array()
    first = tomlkit.inline_table()
    first.update({"node": r.node, "lever_arm": [0.0, 0.0]})
    arr.append(first)
    for f in fits:
        tag = tomlkit.inline_table()
        arm = [round(v, 3) + 0.0 for v in f.lever_arm] if lever_arms else [0.0, 0.0]
        tag.update({"node": f.node, "lever_arm": arm})
        arr.append(tag)
    if lever_arms:
        errs = "; ".join(f"{f.node} +- {f.stderr[0]:.3f}, {f.stderr[1]:.3f} m" for f in fits)
        arr.comment(f"lever arms from this bag's mocap, {errs} (x, y); {r.node} at the body origin")
    else:
        arr.comment(
            f"lever arms not estimated (--no-calibrate): measure {', '.join(f.node for f in fits)} "
            f"from {r.node} (x forward, y left, m)"
        )
    return arr


def to_toml(
    inv: BagInventory,
    d: Draft,
    name: str,
    calibrated: list[str] | None = None,
    *,
    lever_arms: bool = True,
) -> str:
    """The drafted config as TOML text with comments; ``calibrated`` (the robots that get a
    heading offset) marks the draft as one that :func:`calibrate_draft` will fill in;
    ``lever_arms`` writes the extra tags' estimated lever arms (else zeros, to be measured)."""
    doc = tomlkit.document()
    doc.add(
        tomlkit.comment(
            f"Drafted by relloc init from {inv.path}; check every value before trusting it."
        )
    )
    for line in d.notes:
        doc.add(tomlkit.comment(line))
    doc.add("name", name)
    doc.add(tomlkit.comment(d.reference_note))
    doc.add("reference", d.reference)
    doc.add(
        tomlkit.comment(
            "area: the default prior box's size centred on the robots' mocap extent, or that extent "
            f"plus {MARGIN_M:g} m where larger (the filter uses only its size)"
        )
    )
    doc.add("area", [float(v) for v in d.area])
    layout = inv.range_layout or "unknown"
    doc.add(
        tomlkit.comment(
            f"ros_distro: the range messages have the {layout} layout of {inv.range_type or 'Range'}"
        )
    )
    doc.add("ros_distro", distro(inv.range_layout))
    doc.add(
        tomlkit.comment(
            f"mocap_topic: where each body's motion capture is ({inv.mocap_type or 'PoseStamped'})"
        )
    )
    doc.add("mocap_topic", inv.mocap_pattern or TeamConfig.mocap_topic)
    seen = quirks(inv)
    if seen:
        doc.add(tomlkit.nl())
        doc.add(tomlkit.comment("Clock quirks seen in the bag:"))
        for q in seen:
            doc.add(tomlkit.comment(f"  {q}"))
    robots = tomlkit.aot()
    for r in d.robots:
        t = tomlkit.table()
        t.add("name", r.name)
        fits = d.tags_of(r)
        if r.node and fits:
            t.add("tags", _tags(r, fits, lever_arms))
        elif r.node:
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
        if calibrated is not None and r.name in calibrated:
            t.add("heading_offset_deg", 0.0)
            t["heading_offset_deg"].comment(
                "from this bag's mocap: mocap yaw - odometry yaw at the first odometry"
            )
        robots.append(t)
    doc.add("robots", robots)
    uwb = tomlkit.table()
    uwb.add("range_topic", inv.range_pattern or "/uwb/tof/{a}/{b}/distance")
    if inv.range_type and inv.range_type != "sensor_msgs/msg/Range":
        uwb.add("range_type", inv.range_type)
    doc.add(tomlkit.nl())
    if calibrated is None:
        doc.add(
            tomlkit.comment(
                "Pair biases are not calibrated here: relloc calibrate BAG --config THIS.toml"
            )
        )
    else:
        doc.add(
            tomlkit.comment(
                "Pair biases: median of range - mocap distance on this bag (relloc calibrate); the robust "
                "sigma of what is left is in each comment, left unset so the filter's noise model applies"
            )
        )
    doc.add("uwb", uwb)
    return tomlkit.dumps(doc)


def quirks(inv: BagInventory) -> list[str]:
    out = []
    if inv.far_stamps:
        offsets = sorted({round(v) for v in inv.far_stamps.values()})
        shown = ", ".join(f"{v:.0f}" for v in offsets[:3]) + (" ..." if len(offsets) > 3 else "")
        out.append(
            f"{len(inv.far_stamps)} topics stamp far from receive time (stamp - receive: {shown} s)"
        )
    if inv.zero_stamp_topics:
        out.append(f"all-zero header stamps: {', '.join(inv.zero_stamp_topics)}")
    if inv.stale_ranges:
        out.append(
            f"{inv.stale_ranges} of {inv.range_messages} range messages repeat their topic's previous value"
        )
    return out
