"""The TOML text of a drafted team config (:mod:`relloc.drafting.team`), with comments: what was
decided and how sure, the clock quirks seen in the bag."""

from __future__ import annotations

import tomlkit
from tomlkit.items import Item

from relloc.config import TeamConfig
from relloc.drafting.frames import frame_fields
from relloc.drafting.tags import TagFit
from relloc.drafting.team import FLYING_SPREAD_M, MARGIN_M, Draft, Robot
from relloc.sources.inspect_bag import BagInventory

__all__ = ["distro", "quirks", "to_toml"]


def distro(layout: str) -> str:
    return "humble" if layout == "humble" else "jazzy"


def _tags(r: Robot, first: TagFit | None, fits: list[TagFit], lever_arms: bool, dim: int) -> Item:
    """``tags = [...]`` of a robot with extra tags: its first node at the body origin (in 3D at
    its own estimated lever arm, ``first``), each extra one at its estimated lever arm (standard
    errors in the comment), or at the origin to be measured when ``lever_arms`` is false."""
    arr = tomlkit.array()
    placed = [first] if first is not None else []
    zero = [0.0] * dim
    for node, fit in [(r.node, first), *((f.node, f) for f in fits)]:
        tag = tomlkit.inline_table()
        arm = [round(v, 3) + 0.0 for v in fit.lever_arm] if lever_arms and fit else zero
        tag.update({"node": node, "lever_arm": arm})
        arr.append(tag)
    axes = "x, y, z" if dim == 3 else "x, y"
    if lever_arms:
        errs = "; ".join(
            f"{f.node} +- {', '.join(f'{v:.3f}' for v in f.stderr)} m" for f in [*placed, *fits]
        )
        origin = (
            "from the mocap origin, z relative to the tags' mean height (ranges cannot tell it)"
            if first is not None
            else f"{r.node} at the body origin"
        )
        arr.comment(f"lever arms from this bag's mocap, {errs} ({axes}); {origin}")
    else:
        where = "the mocap origin" if dim == 3 else r.node
        nodes = [f.node for f in fits] if dim == 2 else [r.node, *(f.node for f in fits)]
        arr.comment(
            f"lever arms not estimated (--no-calibrate): measure {', '.join(nodes)} "
            f"from {where} (x forward, y left{', z up' if dim == 3 else ''}, m)"
        )
    return arr


def to_toml(
    inv: BagInventory,
    d: Draft,
    name: str,
    calibrated: list[str] | None = None,
    *,
    lever_arms: bool = True,
    range_sigma: float | None = None,
) -> str:
    """The drafted config as TOML text with comments; ``calibrated`` (the robots that get a
    heading offset) marks the draft as one that :func:`calibrate_draft` will fill in;
    ``lever_arms`` writes the extra tags' estimated lever arms (else zeros, to be measured);
    ``range_sigma`` (a flying team's,
    :attr:`relloc.drafting.calibrate.Calibration.range_sigma`) is written as ``[uwb] sigma``
    and ``los_sigma``."""
    doc = tomlkit.document()
    doc.add(
        tomlkit.comment(
            f"Drafted by relloc init from {inv.path}; check every value before trusting it."
        )
    )
    for line in d.notes:
        doc.add(tomlkit.comment(line))
    doc.add("name", name)
    if d.dimension == 3:
        doc.add(
            tomlkit.comment(
                f"dimension: the bodies fly, their mocap heights spread over {d.height_spread:.2f} m "
                f"(more than {FLYING_SPREAD_M:g} m)"
            )
        )
        doc.add("dimension", d.dimension)
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
            t.add("tags", _tags(r, d.first_fit(r), fits, lever_arms, d.dimension))
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
    frames = frame_fields(inv)
    if frames is not None:
        uwb["range_type"].comment("node frames: one topic per node, listing its peers")
        uwb.add("distance_field", frames.distance_field)
        uwb.add("peer_field", frames.peer_field)
    if d.range_delay > 0.0:
        uwb.add("range_delay", d.range_delay)
        uwb["range_delay"].comment(
            "s: the ranges measure the mocap distances this long before their stamps"
        )
    if range_sigma is not None:
        uwb.add("sigma", range_sigma)
        uwb["sigma"].comment("m: the RMS of what the calibrated pair biases leave")
        uwb.add("los_sigma", range_sigma)
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
                + (
                    " (in 3D: [uwb] sigma, the RMS of what is left; each bias_sigma the bias's "
                    "standard error on this bag: for another session, delete them)"
                    if range_sigma is not None
                    else ""
                )
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
