"""Calibration: robust pair biases (synthetic, bag, CSV) and odometry heading offsets."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from relloc.config import RobotConfig, TeamConfig
from relloc.evaluation.calibration import (
    CalibrationError,
    calibrate_pair,
    heading_offsets_from_bag,
    interpolate_track,
    median_standard_error,
    pair_biases_from_bag,
    pair_biases_from_csv,
    rank_node_assignments,
)
from relloc.events import OdometryEvent, RangeEvent
from relloc.ros import messages as rm

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "tiers"
TRAIN_NODES = {1: "n_7", 3: "n_3", 4: "n_4", 5: "n_5"}


# ---------------------------------------------------------------------------- estimator
def test_known_bias_is_recovered_despite_outliers() -> None:
    rng = np.random.default_rng(1)
    true = rng.uniform(1.0, 6.0, 2000)
    measured = true + 0.3 + rng.normal(0.0, 0.05, true.size)
    spikes = rng.random(true.size) < 0.06  # NLOS: ranges far too long
    measured[spikes] += rng.uniform(0.5, 2.0, spikes.sum())
    cal = calibrate_pair(measured, true, source="synthetic")
    assert cal.bias == pytest.approx(0.3, abs=0.01)
    assert cal.scale == 1.0
    assert cal.sigma == pytest.approx(0.05, abs=0.01)
    assert cal.source == "synthetic"


def test_median_standard_error_counts_blocks_not_samples() -> None:
    """Independent errors: about 1.25 sigma / sqrt(n). Errors shared within a block (an
    averaging driver) are as many samples as blocks: the error is that of the blocks."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 100.0, 1.0)  # 100 samples, 20 blocks of 5 s
    true = np.full(t.size, 4.0)
    iid = true + 0.2 + rng.normal(0.0, 0.05, t.size)
    se = median_standard_error(t, iid, true, block_s=5.0, clip=1.0)
    assert se == pytest.approx(1.2533 * 0.05 / math.sqrt(t.size), rel=0.35)
    shared = true + 0.2 + np.repeat(rng.normal(0.0, 0.05, 20), 5)  # one error per block
    se_shared = median_standard_error(t, shared, true, block_s=5.0, clip=1.0)
    assert se_shared is not None and se is not None and se_shared > 1.5 * se
    assert se_shared == pytest.approx(1.2533 * 0.05 / math.sqrt(20), rel=0.5)
    # a garbage range counts at most `clip`; a constant pair is floored; two blocks: unknown
    spiked = iid.copy()
    spiked[10] = 100.0
    assert median_standard_error(t, spiked, true, block_s=5.0, clip=1.0) < 0.02  # 1.25 unclipped
    assert median_standard_error(t, true + 0.2, true, block_s=5.0, clip=1.0) == 0.005
    assert median_standard_error(t[:9], iid[:9], true[:9], block_s=5.0, clip=1.0) is None


def test_scale_is_fitted_only_when_distances_span_enough() -> None:
    rng = np.random.default_rng(2)
    true = rng.uniform(1.0, 6.0, 1500)
    measured = 1.05 * true + 0.1 + rng.normal(0.0, 0.03, true.size)
    measured[::25] += 1.5
    cal = calibrate_pair(measured, true, fit_scale=True)
    assert cal.scale == pytest.approx(1.05, abs=0.01)
    assert cal.bias == pytest.approx(0.1, abs=0.03)
    assert cal.sigma == pytest.approx(0.03, abs=0.01)
    static = np.full(300, 3.0) + rng.normal(0.0, 0.01, 300)
    cal = calibrate_pair(static + 0.4, static, fit_scale=True)
    assert cal.scale == 1.0 and cal.bias == pytest.approx(0.4, abs=1e-6)


def test_estimator_rejects_bad_input() -> None:
    with pytest.raises(CalibrationError):
        calibrate_pair(np.array([]), np.array([]))
    with pytest.raises(CalibrationError):
        calibrate_pair(np.array([1.0, np.nan]), np.array([1.0, 1.0]))
    with pytest.raises(CalibrationError):
        calibrate_pair(np.ones(3), np.ones(4))


def test_interpolation_refuses_gaps_and_extrapolation() -> None:
    times = np.array([0.0, 0.1, 0.2, 1.0, 1.1])
    xs = times * 10.0
    x, _, valid = interpolate_track(
        times, xs, xs, np.array([-0.1, 0.05, 0.2, 0.5, 1.05, 1.2]), max_gap=0.15
    )
    assert valid.tolist() == [False, True, True, False, True, False]
    assert x[1] == pytest.approx(0.5) and x[4] == pytest.approx(10.5)
    _, _, none = interpolate_track(np.array([]), np.array([]), np.array([]), times, max_gap=1.0)
    assert not none.any()


# ---------------------------------------------------------------------------- synthetic bag
def _team() -> TeamConfig:
    return TeamConfig(
        robots=(
            RobotConfig(name="a", uwb_node="n_1", odom_topic="/a/odom", mocap_body="A"),
            RobotConfig(name="b", uwb_node="n_2", odom_topic="/b/odom", mocap_body="B"),
        ),
        reference="b",
    )


def _pose_stamped(t: float, x: float, y: float, yaw: float) -> object:
    types = rm.typestore().types
    return types[rm.POSE_STAMPED](
        header=types["std_msgs/msg/Header"](stamp=rm.time_msg(t), frame_id="world"),
        pose=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=x, y=y, z=0.1),
            orientation=rm.quaternion_from_yaw(yaw),
        ),
    )


def _calibration_bag(path: Path, write: Callable[..., Path], bias: float) -> Path:
    """Robot a drives a circle of radius 2 around static b; ranges read ``true + bias``; the
    odometry frames are rotated by -30 deg (a) and +100 deg (b) against the mocap frame."""
    rng = np.random.default_rng(3)
    msgs = []
    for k in range(1000):  # 10 s of mocap at 100 Hz
        t = 50.0 + k * 0.01
        ang = 0.3 * (t - 50.0)
        msgs.append(
            (
                "/vrpn_client_node/A/pose",
                rm.POSE_STAMPED,
                t,
                _pose_stamped(t, 1.0 + 2.0 * math.cos(ang), 2.0 * math.sin(ang), ang + math.pi / 2),
            )
        )
        msgs.append(
            ("/vrpn_client_node/B/pose", rm.POSE_STAMPED, t, _pose_stamped(t, 1.0, 0.0, 0.4))
        )
    for k in range(60):  # ranges at 10 Hz from 0.5 s to 6.5 s
        t = 50.5 + k * 0.1
        d = 2.0 + bias + rng.normal(0.0, 0.02)
        ev = RangeEvent(t=t, robot_a="a", robot_b="b", distance=d)
        msgs.append(("/uwb/tof/n_1/n_2/distance", rm.RANGE, t + 0.002, rm.range_msg(ev)))
    # at t = 50.2 (first odometry) the mocap yaw of a is pi/2 + 0.3 * 0.2
    for robot, yaw_mocap, offset_deg in (("a", math.pi / 2 + 0.06, -30.0), ("b", 0.4, 100.0)):
        odom_yaw = yaw_mocap - math.radians(offset_deg)
        ev = OdometryEvent(t=50.2, robot=robot, x=0.0, y=0.0, yaw=odom_yaw)
        msgs.append((f"/{robot}/odom", rm.ODOMETRY, 50.201, rm.odometry_msg(ev)))
    msgs.sort(key=lambda m: m[2])
    return write(path, msgs)


def test_pair_bias_from_bag_recovers_known_bias(
    tmp_path: Path, bag_writer: Callable[..., Path]
) -> None:
    bag = _calibration_bag(tmp_path / "cal", bag_writer, bias=0.27)
    cal = pair_biases_from_bag(bag, _team())
    assert set(cal) == {"n_1-n_2"}
    assert cal["n_1-n_2"].bias == pytest.approx(0.27, abs=0.01)
    assert cal["n_1-n_2"].sigma == pytest.approx(0.02, abs=0.01)
    assert cal["n_1-n_2"].source == "cal"
    with pytest.raises(CalibrationError, match="no UWB pair"):
        pair_biases_from_bag(bag, _team(), min_samples=1000)


def test_heading_offsets_from_synthetic_bag(
    tmp_path: Path, bag_writer: Callable[..., Path]
) -> None:
    bag = _calibration_bag(tmp_path / "cal", bag_writer, bias=0.3)
    offsets = heading_offsets_from_bag(bag, _team())
    assert offsets == {"a": pytest.approx(-30.0, abs=0.1), "b": pytest.approx(100.0, abs=0.1)}


# ---------------------------------------------------------------------------- CSV
def _write_csv(path: Path, rows: list[str], header: str | None = None) -> Path:
    header = header or "timestamp,node1,node2,uwb_range,mocap_range,tb_node1_yaw,tb_node2_yaw,error"
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def test_csv_repeated_rows_are_dropped(tmp_path: Path) -> None:
    rows = []
    for k, r in enumerate([1.3, 1.3, 1.3, 1.3, 1.5, 1.7, 1.7]):
        rows.append(f"{k},1.0,3.0,{r},1.0,0,0,{r - 1.0}")
        rows.append(f"{k},3.0,4.0,2.25,2.0,0,0,0.25")
    csv_path = _write_csv(tmp_path / "t.csv", rows)
    cal = pair_biases_from_csv(csv_path, TRAIN_NODES)
    assert set(cal) == {"n_3-n_7", "n_3-n_4"}
    assert cal["n_3-n_7"].bias == pytest.approx(0.5)  # 1.3, 1.5, 1.7 -> median error 0.5
    assert cal["n_3-n_4"].bias == pytest.approx(0.25)
    assert cal["n_3-n_7"].source == "t"
    kept_all = pair_biases_from_csv(csv_path, TRAIN_NODES, drop_repeats=False)
    assert kept_all["n_3-n_7"].bias == pytest.approx(0.3)


def test_csv_errors_are_clear(tmp_path: Path) -> None:
    missing = _write_csv(tmp_path / "m.csv", ["0,1,3,2.0"], header="timestamp,node1,node2,range")
    with pytest.raises(
        CalibrationError, match=r"missing column\(s\) \['uwb_range', 'mocap_range'\]"
    ):
        pair_biases_from_csv(missing, TRAIN_NODES)
    nan = _write_csv(tmp_path / "n.csv", ["0,1,3,2.0,1.7,0,0,0.3", "1,1,3,nan,1.7,0,0,nan"])
    with pytest.raises(CalibrationError, match=r"n\.csv:3: column 'uwb_range' is nan"):
        pair_biases_from_csv(nan, TRAIN_NODES)
    empty_cell = _write_csv(tmp_path / "e.csv", ["0,1,3,,1.7,0,0,0.3"])
    with pytest.raises(CalibrationError, match="not a number"):
        pair_biases_from_csv(empty_cell, TRAIN_NODES)
    unknown = _write_csv(tmp_path / "u.csv", ["0,1,9,2.0,1.7,0,0,0.3"])
    with pytest.raises(CalibrationError, match=r"robot number\(s\) \[9\]"):
        pair_biases_from_csv(unknown, TRAIN_NODES)
    with pytest.raises(CalibrationError, match="not found"):
        pair_biases_from_csv(tmp_path / "absent.csv", TRAIN_NODES)
    (tmp_path / "z.csv").write_text("")
    with pytest.raises(CalibrationError, match="empty"):
        pair_biases_from_csv(tmp_path / "z.csv", TRAIN_NODES)


@pytest.mark.shared_data
def test_training_csv_gives_the_readme_magnitudes(shared_data: Path) -> None:
    cal = pair_biases_from_csv(
        shared_data / "tiers" / "uwb_error" / "train_20221219.csv", TRAIN_NODES
    )
    assert set(cal) == {"n_3-n_4", "n_3-n_5", "n_3-n_7", "n_4-n_5", "n_4-n_7", "n_5-n_7"}
    biases = {k: c.bias for k, c in cal.items()}
    # README: biases of 0.2-0.5 m per pair, not one constant (n_5-n_7 sits just below 0.2)
    assert all(0.15 <= b <= 0.55 for b in biases.values()), biases
    assert max(biases, key=biases.__getitem__) == "n_3-n_5"
    assert biases["n_3-n_5"] == pytest.approx(0.49, abs=0.02)
    assert biases["n_3-n_7"] == pytest.approx(0.37, abs=0.02)
    assert all(0.02 <= c.sigma <= 0.19 for c in cal.values() if c.sigma is not None)
    assert {c.source for c in cal.values()} == {"train_20221219"}


@pytest.mark.shared_data
def test_shortbag_biases_match_the_training_session(shared_data: Path) -> None:
    cfg = TeamConfig.load(CONFIGS / "multi4_shortbag_20221011.toml")
    bag = pair_biases_from_bag(shared_data / "tiers" / "multi4_shortbag_20221011", cfg)
    assert set(bag) == set(cfg.uwb.pairs)
    for key, cal in bag.items():
        assert cal.source == "multi4_shortbag_20221011"
        # the configs hold the CSV calibration: the two sessions agree within a few cm
        assert cal.bias == pytest.approx(cfg.uwb.pairs[key].bias, abs=0.08), key


@pytest.mark.shared_data
def test_heading_offsets_of_the_real_bags(shared_data: Path) -> None:
    for folder in ("pair_range_20220907_1725", "pair_chair_camera_noUWB_20220923"):
        cfg = TeamConfig.load(CONFIGS / f"{folder}.toml")
        offsets = heading_offsets_from_bag(shared_data / "tiers" / folder, cfg)
        # the configs were written from this very function
        assert offsets == {
            r.name: pytest.approx(r.heading_offset_deg, abs=0.05) for r in cfg.robots
        }


@pytest.mark.shared_data
def test_node_mapping_of_the_shortbag_is_unambiguous(shared_data: Path) -> None:
    cfg = TeamConfig.load(CONFIGS / "multi4_shortbag_20221011.toml")
    ranked = rank_node_assignments(shared_data / "tiers" / "multi4_shortbag_20221011", cfg)
    assert len(ranked) == 8 * 7 * 6 * 5  # every assignment of the 8 nodes to 4 robots
    best, runner_up = ranked[:2]
    assert best.nodes == {r.name: r.uwb_node for r in cfg.robots}
    assert best.rms < 0.15 and 0.3 < best.common_bias < 0.4
    assert runner_up.rms > 3 * best.rms
