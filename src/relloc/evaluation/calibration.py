"""Calibration from recordings: UWB range error per transceiver pair, odometry heading offsets.

The derivation: docs/explanation/internals.md, section ``relloc.evaluation.calibration``.
"""

from __future__ import annotations

import csv
import itertools
import math
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relloc import geometry
from relloc.config import PairCalibration, TeamConfig
from relloc.events import Event, GroundTruthEvent, OdometryEvent, RangeEvent, pair_key
from relloc.ranging.dataset import CSV_COLUMNS
from relloc.ros.messages import pose_to_ground_truth, stamp_to_sec
from relloc.sources.rosbag import RosbagSource, recording_name
from relloc.sources.span import SpanSource
from relloc.sources.tracks import interpolate_track

__all__ = [
    "CSV_COLUMNS",
    "CalibrationError",
    "NodeAssignment",
    "calibrate_pair",
    "heading_offsets_from_bag",
    "interpolate_track",
    "median_standard_error",
    "pair_biases_from_bag",
    "pair_biases_from_csv",
    "pair_biases_from_samples",
    "pair_samples_from_bag",
    "rank_node_assignments",
    "residual_rms",
]

"""Columns of the TIERS UWB-error training table."""

_MAD_TO_SIGMA = 1.4826


class CalibrationError(ValueError):
    """The calibration input is unusable (missing columns, NaNs, no overlapping data...)."""


# ---------------------------------------------------------------------------- estimator
def _robust_sigma(residuals: np.ndarray) -> float:
    med = float(np.median(residuals))
    return _MAD_TO_SIGMA * float(np.median(np.abs(residuals - med)))


def _huber_line(x: np.ndarray, y: np.ndarray, iterations: int = 30) -> tuple[float, float]:
    """Robust fit ``y = a x + b`` by iteratively reweighted least squares with Huber weights."""
    A = np.column_stack([x, np.ones_like(x)])
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    for _ in range(iterations):
        r = y - A @ coef
        s = _robust_sigma(r)
        if s <= 0.0:
            break
        k = 1.345 * s
        w = np.minimum(1.0, k / np.maximum(np.abs(r), 1e-12))
        sw = np.sqrt(w)
        new = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)[0]
        if np.allclose(new, coef, atol=1e-9, rtol=0.0):
            coef = new
            break
        coef = new
    return float(coef[0]), float(coef[1])


MIN_SIGMA = 0.01
"""Smallest calibrated range noise (m): UWB ranges come in 1 cm steps, a smaller robust spread
is quantisation (or repeated samples), not a noise to trust."""


def calibrate_pair(
    measured: np.ndarray,
    true: np.ndarray,
    *,
    fit_scale: bool = False,
    min_span: float = 1.0,
    source: str = "",
) -> PairCalibration:
    """Robust ``measured = scale * true + bias`` for one pair from matched samples.

    Without ``fit_scale`` (the default), ``scale = 1`` and ``bias`` is the median error. With
    it, a Huber line is fitted when the true distances span at least ``min_span`` metres (a
    static pair cannot separate a scale from a bias: it then falls back to scale 1).
    ``sigma`` is the robust spread (1.4826 MAD) of what the model leaves unexplained, at least
    ``MIN_SIGMA`` (a filter cannot use a zero noise).
    """
    m = np.asarray(measured, dtype=float)
    d = np.asarray(true, dtype=float)
    if m.shape != d.shape or m.ndim != 1 or m.size == 0:
        raise CalibrationError("need two equally long, non-empty 1-D arrays of samples")
    if not (np.isfinite(m).all() and np.isfinite(d).all()):
        raise CalibrationError("samples contain NaN or infinite values")
    if fit_scale and float(np.ptp(d)) >= min_span:
        scale, bias = _huber_line(d, m)
        residuals = m - (scale * d + bias)
    else:
        scale = 1.0
        bias = float(np.median(m - d))
        residuals = m - d - bias
    return PairCalibration(
        bias=round(bias, 4),
        scale=round(scale, 4),
        sigma=round(max(_robust_sigma(residuals), MIN_SIGMA), 4),
        source=source,
    )


# ---------------------------------------------------------------------------- interpolation
# ---------------------------------------------------------------------------- from a bag
def pair_samples_from_bag(
    path: str | Path,
    config: TeamConfig,
    *,
    max_gap: float = 0.1,
    lag: float | None = None,
    span: tuple[float, float] | None = None,
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Matched samples per node pair: ``pair_key -> (t, measured range, mocap distance)``, the
    distance between the two tags where a config's tags have lever arms.

    ``lag`` (s) compares each range with the mocap distance ``lag`` seconds before its header
    stamp (UWB ranges can trail the geometry by up to about 0.2 s; an averaging driver by half
    its window); ``None``: the config's ``uwb.range_delay``. A flying team (``dimension`` 3)
    is compared in 3D: the mocap heights and the arms' z count (a drone 1 m above its partner
    3 m away is 0.16 m further than the plane says). Ranges without two valid interpolated
    mocap positions are left out. ``span``: only the events between these seconds from the
    recording's start (:mod:`relloc.sources.span`).
    """
    if lag is None:
        lag = config.uwb.range_delay
    flying = config.dimension == 3
    bag = RosbagSource(path, config, ground_truth=True, detections=False, odometry=False)
    source: Iterable[Event] = bag if span is None else SpanSource(bag, span)
    robots = set(config.robot_names)
    tracks: dict[str, list[tuple[float, float, float, float, float]]] = defaultdict(list)
    ranges: dict[str, list[tuple[float, str, str, float, str, str]]] = defaultdict(list)
    for ev in source:
        if isinstance(ev, GroundTruthEvent) and ev.robot in robots:
            z = ev.position[2] if len(ev.position) > 2 else 0.0
            tracks[ev.robot].append((ev.t, ev.position[0], ev.position[1], ev.yaw, z))
        elif isinstance(ev, RangeEvent):
            na, nb = config.range_nodes(ev)
            ranges[ev.node_pair].append((ev.t, ev.robot_a, ev.robot_b, ev.distance, na, nb))
    arrays = {r: np.array(v, dtype=float).reshape(-1, 5) for r, v in tracks.items()}
    arms = config.has_lever_arms
    out: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for key, rows in ranges.items():
        robot_a, robot_b, node_a, node_b = rows[0][1], rows[0][2], rows[0][4], rows[0][5]
        if robot_a not in arrays or robot_b not in arrays:
            continue
        t = np.array([r[0] for r in rows])
        measured = np.array([r[3] for r in rows])
        a, b = arrays[robot_a], arrays[robot_b]
        xa, ya, va = interpolate_track(a[:, 0], a[:, 1], a[:, 2], t - lag, max_gap=max_gap)
        xb, yb, vb = interpolate_track(b[:, 0], b[:, 1], b[:, 2], t - lag, max_gap=max_gap)
        if arms:  # the tags' positions: each at its lever arm in its body's frame
            xa, ya = _tag(a, t - lag, max_gap, xa, ya, config.lever_arm(node_a))
            xb, yb = _tag(b, t - lag, max_gap, xb, yb, config.lever_arm(node_b))
        diff = [xa - xb, ya - yb]
        if flying:
            za, _, _ = interpolate_track(a[:, 0], a[:, 4], a[:, 4], t - lag, max_gap=max_gap)
            zb, _, _ = interpolate_track(b[:, 0], b[:, 4], b[:, 4], t - lag, max_gap=max_gap)
            arm_a, arm_b = config.lever_arm(node_a), config.lever_arm(node_b)
            dz_arms = (arm_a[2] if len(arm_a) > 2 else 0.0) - (arm_b[2] if len(arm_b) > 2 else 0.0)
            diff.append(za - zb + dz_arms)
        ok = va & vb
        if ok.any():
            out[key] = (t[ok], measured[ok], geometry.norm(np.stack(diff, axis=-1))[ok])
    return out


def _tag(
    track: np.ndarray,
    t: np.ndarray,
    max_gap: float,
    x: np.ndarray,
    y: np.ndarray,
    arm: tuple[float, ...],
) -> tuple[np.ndarray, np.ndarray]:
    """A tag at ``arm`` on a body at ``(x, y)``, its heading interpolated from ``track``'s
    ``(t, x, y, yaw)`` rows as a unit vector."""
    if not any(arm[:2]):
        return x, y
    c, s, _ = interpolate_track(
        track[:, 0], np.cos(track[:, 3]), np.sin(track[:, 3]), t, max_gap=max_gap
    )
    n = np.maximum(np.hypot(c, s), 1e-9)
    c, s = c / n, s / n
    return x + c * arm[0] - s * arm[1], y + s * arm[0] + c * arm[1]


def pair_biases_from_bag(
    path: str | Path,
    config: TeamConfig,
    *,
    max_gap: float = 0.1,
    lag: float | None = None,
    fit_scale: bool = False,
    min_samples: int = 20,
    span: tuple[float, float] | None = None,
) -> dict[str, PairCalibration]:
    """Range calibration of every node pair of the team in a recording with motion capture.

    Keys are canonical node pairs (``"n_3-n_7"``); pairs with fewer than ``min_samples``
    matched ranges are left out. ``source`` of each result is the recording's name. Raises
    :class:`~relloc.sources.rosbag.BagError` for an unreadable bag and :class:`CalibrationError`
    if no pair could be matched with motion capture.
    """
    samples = pair_samples_from_bag(path, config, max_gap=max_gap, lag=lag, span=span)
    return pair_biases_from_samples(samples, path, fit_scale=fit_scale, min_samples=min_samples)


def pair_biases_from_samples(
    samples: Mapping[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
    path: str | Path,
    *,
    fit_scale: bool = False,
    min_samples: int = 20,
) -> dict[str, PairCalibration]:
    """:func:`pair_biases_from_bag` from the matched samples of the recording at ``path``
    (:func:`pair_samples_from_bag`), for a caller that reads them once for more than this."""
    name = recording_name(path)
    result = {
        key: calibrate_pair(measured, true, fit_scale=fit_scale, source=name)
        for key, (_, measured, true) in sorted(samples.items())
        if measured.size >= min_samples
    }
    if not result:
        raise CalibrationError(
            f"{path}: no UWB pair of the team has {min_samples}+ ranges with motion capture of "
            "both robots (check uwb_node and mocap_body in the config)"
        )
    return result


def residual_rms(
    samples: Mapping[str, tuple[np.ndarray, np.ndarray, np.ndarray]], clip: float
) -> float | None:
    """The RMS over every matched range of what its pair's median error leaves, each residual
    counted at most ``clip`` (m); ``None`` where nothing matched."""
    left = [_left_by_median(m, d, clip) for _, m, d in samples.values() if m.size]
    if not left:
        return None
    pooled = np.concatenate(left)
    return float(np.sqrt(np.mean(pooled * pooled)))


def _left_by_median(measured: np.ndarray, true: np.ndarray, clip: float) -> np.ndarray:
    """What a pair's median error (its bias) leaves of each range's error, clipped to
    ``+-clip`` (m): one garbage range counts at most ``clip``."""
    r = np.asarray(measured, float) - np.asarray(true, float)
    return np.clip(r - np.median(r), -clip, clip)


MIN_BIAS_SIGMA = 0.005
"""Smallest standard error stated for a calibrated bias (m): half the UWB's 1 cm step."""


def median_standard_error(
    t: np.ndarray, measured: np.ndarray, true: np.ndarray, *, block_s: float, clip: float
) -> float | None:
    """The standard error (m) of a pair's median error (:func:`calibrate_pair`'s ``bias``):
    ``1.2533`` (the median's against the mean's, Gaussian errors) times the mean's, its
    residuals summed per ``block_s`` seconds (neighbouring ranges share their errors: an
    averaging driver, a slow geometry) and each counted at most ``clip``; at least
    ``MIN_BIAS_SIGMA``. ``None`` with fewer than three blocks (no spread to measure)."""
    r = _left_by_median(measured, true, clip)
    blocks = np.floor((np.asarray(t, float) - float(np.min(t))) / block_s).astype(np.intp)
    if np.unique(blocks).size < 3:
        return None
    sums = np.bincount(blocks, weights=r)
    return max(1.2533 * math.sqrt(float(np.sum(sums * sums))) / r.size, MIN_BIAS_SIGMA)


# ---------------------------------------------------------------------------- from the CSV
def _read_csv_columns(csv_path: Path) -> dict[str, np.ndarray]:
    required = ("node1", "node2", "uwb_range", "mocap_range")
    try:
        with csv_path.open(newline="") as fh:
            reader = csv.reader(fh)
            try:
                header = [h.strip() for h in next(reader)]
            except StopIteration:
                raise CalibrationError(f"{csv_path}: the file is empty") from None
            missing = [c for c in required if c not in header]
            if missing:
                raise CalibrationError(
                    f"{csv_path}: missing column(s) {missing}; found {header} "
                    f"(expected the TIERS layout {list(CSV_COLUMNS)})"
                )
            index = {c: header.index(c) for c in required}
            values: dict[str, list[float]] = {c: [] for c in required}
            for lineno, row in enumerate(reader, start=2):
                if not row:
                    continue
                for c, i in index.items():
                    try:
                        v = float(row[i])
                    except (IndexError, ValueError):
                        cell = row[i] if i < len(row) else "<missing>"
                        raise CalibrationError(
                            f"{csv_path}:{lineno}: column {c!r} is not a number: {cell!r}"
                        ) from None
                    if not math.isfinite(v):
                        raise CalibrationError(
                            f"{csv_path}:{lineno}: column {c!r} is {v} (NaN/inf rows are not "
                            "allowed: clean the table first)"
                        )
                    values[c].append(v)
    except FileNotFoundError:
        raise CalibrationError(f"CSV file not found: {csv_path}") from None
    if not values["node1"]:
        raise CalibrationError(f"{csv_path}: no data rows")
    return {c: np.array(v) for c, v in values.items()}


def pair_biases_from_csv(
    csv_path: str | Path,
    node_of_robot: Mapping[int, str],
    *,
    fit_scale: bool = False,
    drop_repeats: bool = True,
) -> dict[str, PairCalibration]:
    """Range calibration per node pair from the TIERS training table.

    ``node_of_robot`` maps the robot numbers of the ``node1``/``node2`` columns to UWB node ids
    (for ``train_20221219.csv``: ``{1: "n_7", 3: "n_3", 4: "n_4", 5: "n_5"}``). With
    ``drop_repeats``, a row whose range equals the previous range of the same pair is dropped
    (the table samples each ~7 Hz pair at 70 Hz). ``source`` is the file's stem.
    """
    csv_path = Path(csv_path)
    cols = _read_csv_columns(csv_path)
    robots_a = cols["node1"].astype(int)
    robots_b = cols["node2"].astype(int)
    unknown = sorted((set(robots_a.tolist()) | set(robots_b.tolist())) - set(node_of_robot))
    if unknown:
        raise CalibrationError(
            f"{csv_path}: robot number(s) {unknown} have no UWB node in node_of_robot "
            f"{dict(node_of_robot)}"
        )
    keys = np.array(
        [
            pair_key(node_of_robot[int(a)], node_of_robot[int(b)])
            for a, b in zip(robots_a, robots_b, strict=True)
        ]
    )
    measured, true = cols["uwb_range"], cols["mocap_range"]
    result: dict[str, PairCalibration] = {}
    for key in sorted(set(keys.tolist())):
        idx = np.flatnonzero(keys == key)
        m, d = measured[idx], true[idx]
        if drop_repeats:
            keep = np.ones(m.size, dtype=bool)
            keep[1:] = m[1:] != m[:-1]
            m, d = m[keep], d[keep]
        result[key] = calibrate_pair(m, d, fit_scale=fit_scale, source=csv_path.stem)
    return result


# ---------------------------------------------------------------------------- heading offsets
def _wrap_deg(angle: float) -> float:
    """Wrap degrees into ``(-180, 180]``."""
    wrapped = math.fmod(angle + 180.0, 360.0)
    if wrapped <= 0.0:
        wrapped += 360.0
    return wrapped - 180.0


def heading_offsets_from_bag(
    path: str | Path,
    config: TeamConfig,
    *,
    max_gap: float = 0.5,
) -> dict[str, float]:
    """Rotation (deg) from each robot's odometry frame to the motion-capture frame.

    For each robot with an ``odom_topic`` and a ``mocap_body``: the mocap yaw at the time of the
    robot's first odometry message (the mocap sample nearest in time, at most ``max_gap``
    seconds away) minus that message's yaw, wrapped to ``(-180, 180]``. This is what
    ``heading_offset_deg`` needs so odometry shares the mocap heading (the paper assumes a
    compass). Robots lacking either topic, or mocap near their first odometry, are left out.
    """
    expected = {r.name for r in config.robots if r.odom_topic and r.mocap_body}
    if not expected:
        return {}
    source = RosbagSource(path, config, detections=False, ranges=False)
    first_odom: dict[str, OdometryEvent] = {}
    mocap: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for ev in source:
        if isinstance(ev, OdometryEvent) and ev.robot in expected and ev.robot not in first_odom:
            first_odom[ev.robot] = ev
        elif isinstance(ev, GroundTruthEvent) and ev.robot in expected:
            mocap[ev.robot].append((ev.t, ev.yaw))
        if first_odom.keys() == expected and ev.t > max(o.t for o in first_odom.values()) + max_gap:
            break  # every robot has its first odometry and the mocap around it
    offsets: dict[str, float] = {}
    for robot in sorted(first_odom, key=config.robot_names.index):
        odom = first_odom[robot]
        samples = mocap.get(robot)
        if not samples:
            continue
        t_mocap, yaw_mocap = min(samples, key=lambda s: abs(s[0] - odom.t))
        if abs(t_mocap - odom.t) > max_gap:
            continue
        offsets[robot] = round(_wrap_deg(math.degrees(yaw_mocap - odom.yaw)), 2)
    return offsets


# ---------------------------------------------------------------------------- node mapping
@dataclass(frozen=True)
class NodeAssignment:
    """One way of putting UWB nodes on the team's robots, scored against motion capture."""

    nodes: dict[str, str]
    """Robot -> UWB node id."""
    rms: float
    """RMS of ``range - mocap distance - common_bias`` over all pairs (errors clipped to
    +-``clip``), m: small when the ranges follow the robots' true distances."""
    common_bias: float
    """Median of ``range - mocap distance`` over all pairs (m); plausible: 0.2-0.5."""
    pair_bias: dict[str, float]
    """Median ``range - mocap distance`` per node pair (m)."""


def rank_node_assignments(
    path: str | Path,
    config: TeamConfig,
    *,
    max_gap: float = 0.1,
    clip: float = 1.0,
) -> list[NodeAssignment]:
    """Score every assignment of the bag's UWB nodes to the team's robots, best first.

    UWB topics name node ids, not robots. For each injective map robot -> node (over all nodes
    seen in ``uwb.range_topic`` topics, anchors included) whose pairs all have a range topic,
    the ranges are compared with the mocap distances of the corresponding ``mocap_body``
    positions (interpolated at each range's header stamp) and scored by the RMS deviation
    from one common bias. The right assignment leaves only the pair biases' spread and noise;
    a wrong one leaves metres. With two robots the two nodes of the pair cannot be told apart
    (both orders score the same). ``config.robots[*].uwb_node`` is not used.
    """
    from relloc.sources.ingest import match_range_topics
    from relloc.sources.rosbag import BagError, read_messages

    robots = [r for r in config.robots if r.mocap_body]
    if len(robots) < 2:
        raise CalibrationError("need at least two robots with a mocap_body")
    with_topics = RosbagSource(path, config, detections=False, ranges=False, odometry=False)
    range_topics = match_range_topics(with_topics.bag_topics, config.uwb.range_topic)
    if not range_topics:
        raise BagError(f"{path}: no topic matches {config.uwb.range_topic!r}")
    mocap_topic = {config.mocap_topic.format(body=r.mocap_body): r.name for r in robots}
    tracks: dict[str, list[tuple[float, float, float]]] = defaultdict(list)
    ranges: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for topic, _, msg in read_messages(path, [*range_topics, *mocap_topic]):
        t = stamp_to_sec(msg.header.stamp)
        if topic in mocap_topic:
            gt = pose_to_ground_truth(msg, "", t=t)  # any of MOCAP_TYPES
            tracks[mocap_topic[topic]].append((t, gt.position[0], gt.position[1]))
        elif math.isfinite(msg.range) and msg.range > 0.0:
            ranges[pair_key(*range_topics[topic])].append((t, float(msg.range)))
    arrays = {r: np.array(v).reshape(-1, 3) for r, v in tracks.items()}

    errors: dict[tuple[str, str, str], np.ndarray] = {}  # (node pair, robot a, robot b)

    def pair_errors(nodes: str, a: str, b: str) -> np.ndarray:
        lo, hi = sorted((a, b))
        key = (nodes, lo, hi)
        if key not in errors:
            rows = np.array(ranges[nodes]).reshape(-1, 2)
            ta, tb = arrays[key[1]], arrays[key[2]]
            xa, ya, va = interpolate_track(
                ta[:, 0], ta[:, 1], ta[:, 2], rows[:, 0], max_gap=max_gap
            )
            xb, yb, vb = interpolate_track(
                tb[:, 0], tb[:, 1], tb[:, 2], rows[:, 0], max_gap=max_gap
            )
            errors[key] = (rows[:, 1] - geometry.norm(np.stack([xa - xb, ya - yb], axis=-1)))[
                va & vb
            ]
        return errors[key]

    names = [r.name for r in robots if r.name in arrays]
    all_nodes = sorted({n for pair in range_topics.values() for n in pair})
    results: list[NodeAssignment] = []
    for perm in itertools.permutations(all_nodes, len(names)):
        node_of = dict(zip(names, perm, strict=True))
        per_pair: dict[str, np.ndarray] = {}
        for a, b in itertools.combinations(names, 2):
            key = pair_key(node_of[a], node_of[b])
            if key not in ranges:
                break
            per_pair[key] = pair_errors(key, a, b)
        else:
            pooled = np.concatenate(list(per_pair.values()))
            if pooled.size == 0:
                continue
            common = float(np.median(pooled))
            rms = float(np.sqrt(np.mean(np.clip(pooled - common, -clip, clip) ** 2)))
            results.append(
                NodeAssignment(
                    nodes=node_of,
                    rms=round(rms, 4),
                    common_bias=round(common, 4),
                    pair_bias={k: round(float(np.median(v)), 4) for k, v in per_pair.items()},
                )
            )
    results.sort(key=lambda r: (r.rms, sorted(r.nodes.items())))
    return results
