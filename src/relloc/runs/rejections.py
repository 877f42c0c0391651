"""What the rejection counters mean, in one place, for every command that prints them.

Sources (:class:`~relloc.sources.ingest.IngestStats.rejected`) and localizers
(:attr:`~relloc.localizers.base.Localizer.rejected`) count what they dropped by a short
reason name. A user reading ``repeated_range: 539`` needs to know what was dropped and whether
it changes the result; :data:`REASONS` says both, and :func:`rejection_lines` turns a counter
into readable lines. A reason missing from the table is still printed, marked "see the log".
"""

from __future__ import annotations

from collections.abc import Mapping

REASONS: dict[str, tuple[str, str]] = {
    # ------------------------------------------------------------------ sources
    "decode_error": (
        "messages that could not be decoded",
        "check the message types; the rest is used",
    ),
    "unknown_key": (
        "Zenoh keys that belong to no robot of the team",
        "harmless with --subscribe-all",
    ),
    "queue_full": (
        "messages dropped because the engine fell behind",
        "matters: lower the particle count",
    ),
    "late": ("messages older than the reorder buffer could still place", "harmless if few"),
    "range_nonfinite": (
        "UWB ranges that were NaN or infinite",
        "harmless: a driver's invalid reading",
    ),
    "range_nonpositive": ("UWB ranges of zero or less", "harmless: a driver's invalid reading"),
    "detection_zero_position": (
        "detections at exactly (0, 0, 0)",
        "harmless: the camera's value for a box without depth",
    ),
    "bag_damaged": (
        "times the bag's storage was found damaged (the rest read as far as readable)",
        "matters: messages lost",
    ),
    "malformed_row": (
        "MRCLAM rows with another column count, text, NaN or infinity (warned by file and line)",
        "harmless if few: the rest of the file is used",
    ),
    "detection_nonfinite": ("detections with NaN or infinite positions", "harmless"),
    "detection_behind_camera": ("detections with depth <= 0", "harmless: impossible positions"),
    # ------------------------------------------------------------------ localizers
    "repeated_range": (
        "ranges equal to their pair's previous one",
        "expected on the TIERS recordings: a stale sample re-published is not new evidence",
    ),
    "late_measurement": (
        "measurements older than the filter's time",
        "matters if many: raise --reorder-window",
    ),
    "time_jump": ("events stamped far ahead of the team's clock", "matters: a clock problem"),
    "time_jump_backward": (
        "events stamped far behind the team's clock",
        "matters: a clock problem",
    ),
    "invalid_time": ("events with a NaN or infinite time stamp", "matters: a driver problem"),
    "invalid_range": ("ranges that are NaN, infinite or negative", "harmless if few"),
    "invalid_odometry": ("odometry with NaN or infinite values", "matters if many"),
    "out_of_order_odometry": (
        "odometry not newer than the robot's previous one",
        "harmless if few",
    ),
    "unknown_robot": ("events about a robot the team does not have", "check the config"),
    "unknown_event_type": ("events no measurement model fuses", "harmless"),
    "unknown_node_pair": (
        "ranges of a node pair without a bias column (online biases)",
        "check [uwb.pairs]",
    ),
    "self_range": ("ranges from a robot to itself", "check the UWB node ids"),
    "self_observation": ("detections relating a robot to itself", "harmless"),
    "invalid_relative_observation": (
        "relative positions that are NaN or infinite",
        "harmless if few",
    ),
}
"""Reason -> (what was dropped, whether it matters)."""


def rejection_lines(who: str, counts: Mapping[str, int]) -> list[str]:
    """One line per non-zero counter: ``"<who> dropped 539 <what> [repeated_range]: <matters>"``;
    an empty list when nothing was dropped."""
    lines = []
    for reason, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])):
        if not n:
            continue
        what, matters = REASONS.get(reason, ("events", "see the log (-v)"))
        lines.append(f"{who} dropped {n} {what} [{reason}]: {matters}")
    return lines
