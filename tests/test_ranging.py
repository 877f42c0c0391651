"""Range-error data handling, evaluation and the run-time RangeCorrector, without torch.

The corrector and the evaluation are exercised with a hand-built ONNX model whose prediction is
known exactly (residual ``0.1 * yaw_a`` of the newest frame, sigma ``0.02 + 0.01 |yaw_a|``,
beside the manifest's pair constant 0.3), so every corrected distance and sigma can be checked
to the float.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from relloc.events import DetectionEvent, OdometryEvent, RangeEvent
from relloc.ranging.dataset import (
    DEFAULT_NODE_MAP,
    RangingDataError,
    block_split,
    drop_repeats,
    load_csv,
    make_windows,
    parse_node_map,
    split_bounds,
)
from relloc.ranging.manifest import ModelDirError, find_model_dirs, read_manifest, write_manifest
from relloc.ranging.synthetic import synthetic_rows, write_synthetic_csv

HEADER = "timestamp,node1,node2,uwb_range,mocap_range,tb_node1_yaw,tb_node2_yaw,error\n"


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# ---------------------------------------------------------------------------- CSV loading
def test_node_map_parsing() -> None:
    assert parse_node_map("1=n_7, 3=n_3,4.0=n_4") == {"1": "n_7", "3": "n_3", "4": "n_4"}
    with pytest.raises(RangingDataError, match="must look like"):
        parse_node_map("1:n_7")
    with pytest.raises(RangingDataError, match="one node to two robots"):
        parse_node_map("1=n_7,3=n_7")


def test_load_csv_keys_by_node_pair_in_canonical_order(tmp_path: Path) -> None:
    csv = write(
        tmp_path / "a.csv",
        HEADER
        + "10.0,1.0,3.0,4.40,4.10,0.5,-1.0,0.30\n"  # robot 1 = n_7, robot 3 = n_3
        + "10.1,3.0,1.0,4.50,4.15,-1.1,0.6,0.35\n",  # same pair named the other way round
    )
    series = load_csv(csv, DEFAULT_NODE_MAP)
    assert list(series) == ["n_3-n_7"]
    s = series["n_3-n_7"]
    assert (s.node_a, s.node_b) == ("n_3", "n_7")
    np.testing.assert_allclose(s.yaw_a, [-1.0, -1.1])  # heading of n_3's robot both times
    np.testing.assert_allclose(s.yaw_b, [0.5, 0.6])
    np.testing.assert_allclose(s.error, [0.30, 0.35])


def test_error_column_may_be_replaced_by_mocap_range(tmp_path: Path) -> None:
    csv = write(
        tmp_path / "b.csv",
        "timestamp,node1,node2,uwb_range,mocap_range,tb_node1_yaw,tb_node2_yaw\n"
        "1.0,n_3,n_7,4.40,4.10,0.0,0.0\n",
    )
    assert load_csv(csv)["n_3-n_7"].error == pytest.approx([0.30])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("timestamp,node1,node2,uwb_range,error\n1,1,3,4.0,0.3\n", r"missing column.*tb_node1_yaw"),
        ("timestamp,node1,node2,uwb_range,tb_node1_yaw,tb_node2_yaw\n1,1,3,4,0,0\n", "error"),
        (HEADER + "1.0,1,3,nan,4.1,0.0,0.0,0.3\n", r":2: column 'uwb_range' is 'nan'"),
        (HEADER + "1.0,1,3,4.4,4.1,,0.0,0.3\n", r":2: column 'tb_node1_yaw' is '', not a number"),
        (HEADER + "1.0,1,3,4.4,4.1,0.0,0.0,0.3\n2.0,1,3,4.4\n", r":3: 4 fields"),
        (HEADER + "1.0,1,2,4.4,4.1,0.0,0.0,0.3\n", r"robot '2' is not in the node map"),
        ("", "empty"),
        (HEADER, "no data rows"),
    ],
)
def test_bad_csv_raises_one_clear_error(tmp_path: Path, text: str, message: str) -> None:
    with pytest.raises(RangingDataError, match=message):
        load_csv(write(tmp_path / "bad.csv", text))


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RangingDataError, match="not found"):
        load_csv(tmp_path / "nope.csv")


def test_repeats_dropped_and_windows_chronological(tmp_path: Path) -> None:
    csv = write_synthetic_csv(tmp_path / "s.csv", n_samples=200, repeat_probability=0.3, seed=1)
    s = load_csv(csv)["n_3-n_7"]
    clean, dropped = drop_repeats(s)
    assert dropped > 20 and len(clean) + dropped == len(s)
    assert np.all(clean.range[1:] != clean.range[:-1])
    _end_train, end_val = split_bounds(len(clean), (0.7, 0.1, 0.2))
    w, y, idx = make_windows(clean, 5, slice(end_val, None))
    assert w.shape == (len(clean) - end_val, 5, 3)
    assert idx[0] == end_val and idx[-1] == len(clean) - 1
    np.testing.assert_array_equal(y, clean.error[idx])
    # A window ends at its target and reaches back in time, oldest first.
    np.testing.assert_array_equal(w[0, :, 0], clean.range[end_val - 4 : end_val + 1])
    w_all, _, idx_all = make_windows(clean, 5)
    assert idx_all[0] == 4 and len(w_all) == len(clean) - 4
    with pytest.raises(ValueError, match="sum"):
        split_bounds(10, (0.5, 0.1, 0.1))


def test_block_split_spreads_validation_blocks_with_gaps() -> None:
    split = block_split(1000, (0.7, 0.1, 0.2), val_blocks=3, gap=10)
    assert split.end_dev == 800 and split.n == 1000
    # 100 validation rows: three blocks of 33, centred in thirds of the 800 rows before test.
    assert split.val_blocks == ((117, 150), (384, 417), (650, 683))
    assert len(split.val) == 99
    train = set(split.train.tolist())
    assert not train & set(split.val.tolist())
    for start, stop in split.val_blocks:  # gap rows on both sides excluded from training
        assert not train & set(range(start - 10, stop + 10))
    assert max(train) == 789 and min(train) == 0  # a gap before the test part too
    assert len(train) == 800 - 99 - 6 * 10 - 10
    # Indices as targets: windows only where the history is full.
    csv_series = load_csv_from_rows(40)
    w, _, idx = make_windows(csv_series, 5, np.array([0, 3, 4, 10, 39, 40]))
    assert idx.tolist() == [4, 10, 39] and w.shape == (3, 5, 3)
    with pytest.raises(ValueError, match="val_blocks"):
        block_split(100, val_blocks=0)


def load_csv_from_rows(n: int):  # type: ignore[no-untyped-def]
    from relloc.ranging.dataset import PairSeries

    x = np.arange(n, dtype=float)
    return PairSeries("n_3-n_7", "n_3", "n_7", x, 3 + 0.01 * x, 0 * x, 0 * x, 0.1 + 0 * x)


def test_online_offset_starts_at_the_prior_and_moves_to_the_session_mean() -> None:
    from relloc.ranging.evaluate import online_offset

    values = np.full(200, 0.5)
    est = online_offset(values, prior=0.3, weight=20.0)
    assert est[0] == pytest.approx(0.3)  # causal: nothing seen yet
    assert est[20] == pytest.approx((20 * 0.3 + 20 * 0.5) / 40)
    assert est[-1] == pytest.approx((20 * 0.3 + 199 * 0.5) / 219)


def test_synthetic_error_is_the_documented_function() -> None:
    rows = synthetic_rows(("1", "3"), n_samples=50, noise=0.0, repeat_probability=0.0)
    for _t, _r1, _r2, measured, distance, _yaw1, yaw3, error in rows:
        assert error == pytest.approx(measured - distance)
        # Robot 3 carries n_3, the first node of "n_3-n_7"; ranges are in 1 cm steps.
        assert error == pytest.approx(0.3 + 0.1 * math.cos(yaw3 - 0.5), abs=0.0051)


# ---------------------------------------------------------------------------- known ONNX model
def known_onnx(n_steps: int, scale: float = 0.1, offset: float = 0.0) -> bytes:
    """ONNX graph: raw window (B, n_steps, 3) -> residual ``offset + scale * yaw_a`` and sigma
    ``0.02 + 0.01 * |yaw_a|`` of the newest frame."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    def const(name: str, values: list[int] | list[float], dtype: int) -> onnx.TensorProto:
        return helper.make_tensor(name, dtype, [len(values)], values)

    nodes = [
        helper.make_node("Slice", ["window", "starts", "ends", "axes"], ["last"]),
        helper.make_node("Reshape", ["last", "shape"], ["col"]),
        helper.make_node("Mul", ["col", "scale"], ["scaled"]),
        helper.make_node("Add", ["scaled", "offset"], ["residual"]),
        helper.make_node("Abs", ["col"], ["abs"]),
        helper.make_node("Mul", ["abs", "s_scale"], ["s_scaled"]),
        helper.make_node("Add", ["s_scaled", "s_floor"], ["sigma"]),
    ]
    out = [
        helper.make_tensor_value_info(n, TensorProto.FLOAT, ["batch", 1])
        for n in ("residual", "sigma")
    ]
    graph = helper.make_graph(
        nodes,
        "known",
        [helper.make_tensor_value_info("window", TensorProto.FLOAT, ["batch", n_steps, 3])],
        out,
        [
            const("starts", [n_steps - 1, 1], TensorProto.INT64),
            const("ends", [n_steps, 2], TensorProto.INT64),
            const("axes", [1, 2], TensorProto.INT64),
            const("shape", [-1, 1], TensorProto.INT64),
            const("scale", [scale], TensorProto.FLOAT),
            const("offset", [offset], TensorProto.FLOAT),
            const("s_scale", [0.01], TensorProto.FLOAT),
            const("s_floor", [0.02], TensorProto.FLOAT),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return model.SerializeToString()


def known_model_dir(
    path: Path,
    n_steps: int = 3,
    pairs: tuple[str, ...] = ("n_3-n_7",),
    offset: str = "manifest",
    **entry: object,
) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    data = known_onnx(n_steps)
    entries = {}
    for pair in pairs:
        (path / f"{pair}.onnx").write_bytes(data)
        entries[pair] = {
            "nodes": pair.split("-"),
            "onnx": f"{pair}.onnx",
            "residual_min": -1.0,
            "residual_max": 1.0,
            "train_bias": 0.3,
            **entry,
        }
    write_manifest(
        path,
        {
            "variant": "stacked",
            "n_steps": n_steps,
            "offset": offset,
            "constant": 0.3,
            "pairs": entries,
        },
    )
    return path


# ---------------------------------------------------------------------------- RangeCorrector
def rng_ev(
    t: float, d: float, a: str = "turtle01", b: str = "turtle03", na: str = "n_7", nb: str = "n_3"
) -> RangeEvent:
    return RangeEvent(t, a, b, d, node_a=na, node_b=nb)


def odom(t: float, robot: str, yaw: float) -> OdometryEvent:
    return OdometryEvent(t, robot, 0.0, 0.0, yaw)


def test_corrector_pass_through_reasons_and_correction(tmp_path: Path) -> None:
    from relloc.stages.range_correction import OUTCOMES, RangeCorrector

    c = RangeCorrector.from_dir(known_model_dir(tmp_path / "m", n_steps=3))
    out = c.correct(rng_ev(0.0, 4.0))
    assert out.corrected is False and out.distance == 4.0
    assert c.stats["no_yaw"] == 1
    # turtle01 carries n_7 (second in "n_3-n_7"), turtle03 carries n_3 (first): yaw_a is
    # turtle03's heading.
    c.observe(odom(0.0, "turtle01", 1.0))
    c.observe(odom(0.0, "turtle03", -0.5))
    c.observe(DetectionEvent(0.0, "turtle01"))  # ignored
    assert c.correct(rng_ev(0.1, 4.00)).corrected is False
    assert c.correct(rng_ev(0.2, 4.00)).corrected is False  # repeat: not a new frame
    assert c.correct(rng_ev(0.3, 4.02)).corrected is False
    assert c.stats["window_not_full"] == 3
    c.observe(odom(0.35, "turtle01", 1.0))
    c.observe(odom(0.35, "turtle03", -0.4))
    out = c.correct(rng_ev(0.4, 4.05))  # third distinct range: window full
    assert out.corrected is True
    assert out.distance == pytest.approx(4.05 - (0.3 + 0.1 * -0.4), abs=1e-6)
    assert out.sigma == pytest.approx(0.02 + 0.01 * 0.4, abs=1e-7)  # the model's uncertainty
    assert (out.robot_a, out.node_a, out.t) == ("turtle01", "n_7", 0.4)
    # The same measurement again gets the same correction without a new frame.
    again = c.correct(rng_ev(0.45, 4.05))
    assert again.corrected and again.distance == pytest.approx(out.distance)
    assert again.sigma == out.sigma
    assert c.stats["corrected"] == 1 and c.stats["corrected_repeat"] == 1
    # Naming the robots the other way round changes nothing.
    swapped = c.correct(rng_ev(0.5, 4.07, "turtle03", "turtle01", "n_3", "n_7"))
    assert swapped.distance == pytest.approx(4.07 - (0.3 + 0.1 * -0.4), abs=1e-6)
    # Other pass-through reasons.
    assert not c.correct(rng_ev(0.5, 3.0, na="n_4", nb="n_5")).corrected
    assert c.stats["no_model"] == 1
    assert not c.correct(rng_ev(0.2, 4.2)).corrected
    assert c.stats["out_of_order"] == 1
    assert not c.correct(rng_ev(0.6, float("nan"))).corrected
    assert not c.correct(rng_ev(0.6, -1.0)).corrected
    assert c.stats["invalid_range"] == 2
    assert c.correct(out) is out and c.stats["already_corrected"] == 1
    assert not c.correct(rng_ev(5.0, 4.3)).corrected  # heading 4.65 s old
    assert c.stats["stale_yaw"] == 1
    assert sum(c.stats[k] for k in OUTCOMES) == 13  # every range counted once


def test_corrector_gap_resets_window_and_told_yaws(tmp_path: Path) -> None:
    from relloc.stages.range_correction import RangeCorrector

    c = RangeCorrector.from_dir(known_model_dir(tmp_path / "m", n_steps=2), max_gap=1.0)
    c.set_yaw("turtle01", 0.0, 0.0)
    c.set_yaw("turtle03", 0.0, 0.2)
    assert not c.correct(rng_ev(0.0, 4.0)).corrected
    assert c.correct(rng_ev(0.1, 4.1)).corrected
    c.set_yaw("turtle01", 3.0, 0.0)
    c.set_yaw("turtle03", 3.0, 0.2)
    assert not c.correct(rng_ev(3.0, 4.2)).corrected  # 2.9 s gap: window starts again
    assert c.stats["window_reset"] == 1 and c.stats["window_not_full"] == 2
    out = c.correct(rng_ev(3.1, 4.3))
    assert out.corrected and out.distance == pytest.approx(4.3 - 0.32, abs=1e-6)
    c.reset()
    assert not c.stats and not c.correct(rng_ev(4.0, 4.0)).corrected


def test_corrector_clips_to_training_errors(tmp_path: Path) -> None:
    from relloc.stages.range_correction import RangeCorrector

    d = known_model_dir(tmp_path / "m", n_steps=1, residual_min=-0.3, residual_max=0.05)
    c = RangeCorrector.from_dir(d, yaw_provider=lambda robot, t: 3.0)  # residual 0.3 m
    out = c.correct(rng_ev(0.0, 4.0))
    assert out.corrected and out.distance == pytest.approx(4.0 - (0.3 + 0.05))
    assert c.stats["clipped"] == 1
    c2 = RangeCorrector.from_dir(d, yaw_provider=lambda robot, t: -2.0)  # -0.2: inside
    assert c2.correct(rng_ev(0.0, 4.0)).distance == pytest.approx(4.0 - (0.3 - 0.2), abs=1e-6)
    assert c2.stats["clipped"] == 0
    # Batch inference clips the same way.
    from relloc.ranging.inference import ModelSet

    model = ModelSet.load(d)["n_3-n_7"]
    windows = np.array([[[4.0, 3.0, 0.0]], [[4.0, -2.0, 0.0]], [[4.0, -5.0, 0.0]]])
    assert model.predict(windows) == pytest.approx([0.35, 0.1, 0.0], abs=1e-6)


def test_fallback_pair_gets_the_constant_and_its_sigma(tmp_path: Path) -> None:
    """A pair the training guard marked fallback: the constant alone, from the first range."""
    from relloc.ranging.evaluate import evaluate
    from relloc.ranging.inference import ModelSet
    from relloc.stages.range_correction import RangeCorrector

    d = known_model_dir(
        tmp_path / "models" / "stacked", n_steps=3, fallback=True, fallback_sigma=0.07
    )
    models = ModelSet.load(d)
    assert models["n_3-n_7"].fallback
    residual, sigma = models["n_3-n_7"].predict_residual(np.ones((2, 3, 3)))
    assert residual.tolist() == [0.0, 0.0] and sigma.tolist() == [0.07, 0.07]
    c = RangeCorrector(models)
    out = c.correct(rng_ev(0.0, 4.0))  # no heading, no full window: not needed
    assert out.corrected and out.distance == pytest.approx(3.7) and out.sigma == 0.07
    assert c.stats["fallback"] == 1 and c.stats["corrected"] == 0
    # Evaluation honours the guard: the model's MSE is the constant's.
    report = evaluate(known_csv(tmp_path / "k.csv"), [tmp_path / "models"])
    m = report["methods"]
    assert m["stacked"]["fallback_pairs"] == ["n_3-n_7"]
    assert m["stacked"]["mean_mse"] == pytest.approx(m["bias"]["mean_mse"])
    # A fallback with no sigma is a malformed directory.
    bad = known_model_dir(tmp_path / "bad", n_steps=3, fallback=True)
    with pytest.raises(ModelDirError, match="fallback_sigma"):
        ModelSet.load(bad)


def test_evaluate_scores_as_deployed_with_the_support_guard(tmp_path: Path) -> None:
    """``relloc ranging eval`` scores what the run time does: a window outside the pair's
    training support gets the constant; ``support_guard=False`` scores the network there."""
    from relloc.ranging.evaluate import evaluate
    from relloc.ranging.support import YAW_CELLS, InputSupport

    support = InputSupport(
        (0.0, -9.0, -9.0, -9.0), (4.6, 9.0, 9.0, 9.0), frozenset(range(YAW_CELLS**2))
    )
    known_model_dir(tmp_path / "models" / "stacked", n_steps=3, support=support.to_json())
    csv = known_csv(tmp_path / "k.csv")
    guarded = evaluate(csv, [tmp_path / "models"])["methods"]
    raw = evaluate(csv, [tmp_path / "models"], support_guard=False)["methods"]
    assert raw["stacked"]["mean_mse"] < 1e-12 and "out_of_support" not in raw["stacked"]
    outside = guarded["stacked"]["out_of_support"]
    assert 0 < outside < 78  # ranges above 4.6 m, not the others
    # outside, the constant 0.3 misses by 0.1 yaw: the guarded MSE is the bias's on those rows
    assert 0.0 < guarded["stacked"]["mean_mse"] < guarded["bias"]["mean_mse"]


def test_filter_offset_mode_leaves_the_constant_to_the_filter(tmp_path: Path) -> None:
    """offset = filter: only the learned residual is removed, the range stays uncorrected."""
    from relloc.stages.range_correction import RangeCorrector

    d = known_model_dir(tmp_path / "m", n_steps=1, offset="filter")
    c = RangeCorrector.from_dir(d, yaw_provider=lambda robot, t: 0.5)
    out = c.correct(rng_ev(0.0, 4.0))
    assert not out.corrected and out.distance == pytest.approx(4.0 - 0.05, abs=1e-6)
    assert out.sigma == pytest.approx(0.025, abs=1e-7)
    assert c.stats["corrected"] == 1
    assert c.correct(out) is out and c.stats["already_corrected"] == 1  # never twice
    manifest = RangeCorrector.from_dir(d, offset="manifest", yaw_provider=lambda r, t: 0.5)
    assert manifest.correct(rng_ev(0.0, 4.0)).distance == pytest.approx(4.0 - 0.35, abs=1e-6)
    with pytest.raises(ValueError, match="offset"):
        RangeCorrector.from_dir(d, offset="online")


def test_corrector_uses_team_heading_offsets(tmp_path: Path) -> None:
    from relloc.config import RobotConfig, TeamConfig
    from relloc.stages.range_correction import RangeCorrector

    team = TeamConfig(
        robots=(
            RobotConfig("turtle01", uwb_node="n_7"),
            RobotConfig("turtle03", uwb_node="n_3", heading_offset_deg=90.0),
        ),
        reference="turtle01",
    )
    c = RangeCorrector.from_config(team, known_model_dir(tmp_path / "m", n_steps=1))
    c.observe(odom(0.0, "turtle01", 0.0))
    c.observe(odom(0.0, "turtle03", 0.1))
    out = c.correct(rng_ev(0.0, 4.0))
    assert out.distance == pytest.approx(4.0 - (0.3 + 0.1 * (0.1 + math.pi / 2)), abs=1e-6)


def test_runtime_imports_no_torch() -> None:
    code = (
        "import sys; import relloc.stages.range_correction, relloc.ranging.evaluate, "
        "relloc.cli.ranging; assert 'torch' not in sys.modules, 'torch imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


# ---------------------------------------------------------------------------- evaluation
def known_csv(path: Path, n: int = 80, seed: int = 0) -> Path:
    """Pair n_3-n_7 (robots 3 and 1) whose error is exactly the known model's prediction."""
    rng = np.random.default_rng(seed)
    lines = [HEADER]
    for i in range(n):
        yaw3 = float(rng.uniform(-3, 3))
        err = 0.3 + 0.1 * yaw3
        dist = 4.0 + 0.01 * i
        lines.append(f"{i * 0.15},1,3,{dist + err!r},{dist!r},0.0,{yaw3!r},{err!r}\n")
    return write(path, "".join(lines))


def test_evaluate_scores_models_and_baselines(tmp_path: Path) -> None:
    from relloc.ranging.evaluate import evaluate

    models = known_model_dir(tmp_path / "models" / "stacked", n_steps=3)
    report = evaluate(known_csv(tmp_path / "k.csv"), [tmp_path / "models"])
    assert report["part"] == "all"  # not the training CSV
    assert report["pairs"] == ["n_3-n_7"] and report["n_targets"]["n_3-n_7"] == 78
    m = report["methods"]
    assert set(m) == {"zero", "bias", "constant", "stacked", "bias+online", "stacked+online"}
    assert m["stacked"]["mean_mse"] < 1e-12
    assert m["stacked+online"]["mean_mse"] < 1e-12  # the right offset stays put
    assert m["constant"]["mean_mse"] == pytest.approx(m["bias"]["mean_mse"])  # both 0.3
    assert m["stacked"]["fallback_pairs"] == []
    # sigma 0.02 + 0.01 |yaw| against errors of 0: z = 0, all inside two sigmas.
    assert m["stacked"]["sigma_z_rms"] < 1e-4 and m["stacked"]["sigma_cover_2"] == 1.0
    assert m["bias"]["mean_mse"] == pytest.approx(0.01 * 3.0, rel=0.5)  # var of 0.1 * U(-3, 3)
    assert m["zero"]["mean_mse"] > m["bias"]["mean_mse"]
    assert m["stacked"]["time_per_prediction_s"]["median"] < 0.01
    assert read_manifest(models)["variant"] == "stacked"


def test_eval_cli_writes_json_and_reports_bad_input(tmp_path: Path) -> None:
    from relloc.cli.ranging import main

    known_model_dir(tmp_path / "m", n_steps=3)
    csv = known_csv(tmp_path / "k.csv")
    out = tmp_path / "r" / "eval.json"
    assert (
        main(["ranging", "eval", str(csv), "--models", str(tmp_path / "m"), "--json", str(out)])
        == 0
    )
    report = json.loads(out.read_text())["methods"]["stacked"]
    assert report["mean_mse"] < 1e-12 and report["out_of_support"] == 0  # guarded by default
    raw = tmp_path / "r" / "raw.json"
    args = ["ranging", "eval", str(csv), "--models", str(tmp_path / "m"), "--no-support-guard"]
    assert main([*args, "--json", str(raw)]) == 0
    assert "out_of_support" not in json.loads(raw.read_text())["methods"]["stacked"]
    bad = write(tmp_path / "bad.csv", "timestamp,node1\n1,1\n")
    assert main(["ranging", "eval", str(bad), "--models", str(tmp_path / "m")]) == 2
    assert main(["ranging", "eval", str(csv), "--models", str(tmp_path / "nothing")]) == 2


def test_model_dir_errors(tmp_path: Path) -> None:
    with pytest.raises(ModelDirError, match=r"no manifest\.json"):
        read_manifest(tmp_path)
    with pytest.raises(ModelDirError, match="neither a model directory"):
        find_model_dirs([tmp_path])
    d = known_model_dir(tmp_path / "m")
    (d / "n_3-n_7.onnx").unlink()
    with pytest.raises(ModelDirError, match="missing"):
        read_manifest(d)


def test_corrector_passes_the_raw_range_when_the_model_answers_nan_or_inf(tmp_path: Path) -> None:
    from relloc.stages.range_correction import RangeCorrector

    d = known_model_dir(tmp_path / "m", n_steps=1)
    (d / "n_3-n_7.onnx").write_bytes(known_onnx(1, scale=math.inf))  # inf * yaw: inf, or NaN at 0
    c = RangeCorrector.from_dir(d, yaw_provider=lambda robot, t: 3.0)
    out = c.correct(rng_ev(0.0, 4.0))
    assert not out.corrected and out.distance == 4.0
    assert c.stats["model_nonfinite"] == 1


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"residual_min": 1.0, "residual_max": -1.0},
            "residual_min 1.0 must be below residual_max -1.0",
        ),
        ({"offset": "online"}, "offset 'online' is not one of"),
        ({"n_steps": 5}, r"not \(B, 5, 3\)"),
        ({"n_steps": "ten"}, "malformed manifest"),
        ({"pairs": []}, "must map each node pair"),
        ({"pairs": {}}, "lists no pair"),
        ({"garbage": True}, "onnxruntime cannot load it"),
    ],
)
def test_a_model_directory_that_cannot_serve_is_one_clear_error(
    tmp_path: Path, change: dict, message: str
) -> None:
    from relloc.ranging.inference import ModelSet

    d = known_model_dir(tmp_path / "m", n_steps=3)
    manifest = json.loads((d / "manifest.json").read_text())
    if change.pop("garbage", False):
        (d / "n_3-n_7.onnx").write_bytes(b"not a model")
    for key in ("residual_min", "residual_max"):
        if key in change:
            manifest["pairs"]["n_3-n_7"][key] = change.pop(key)
    manifest.update(change)
    (d / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ModelDirError, match=message):
        ModelSet.load(d)
