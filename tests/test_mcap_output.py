"""``relloc run --mcap``: the run as ROS 2 messages in an MCAP file, read back with the
independent ``mcap`` / ``mcap-ros2-support`` reader (not relloc's or rosbags' codec)."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from relloc.estimate import BODY_FRAME, Estimate
from relloc.ros.estimate_msgs import NOT_ESTIMATED

make_reader = pytest.importorskip("mcap.reader").make_reader
DecoderFactory = pytest.importorskip("mcap_ros2.decoder").DecoderFactory


def read_mcap(path: Path) -> dict[str, list[tuple[str, int, Any]]]:
    """Topic -> [(schema name, log time in ns, decoded message)], in file order."""
    out: dict[str, list[tuple[str, int, Any]]] = defaultdict(list)
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            assert channel.message_encoding == "cdr"
            out[channel.topic].append((schema.name, message.log_time, decoded))
    return out


def test_run_writes_mcap_that_an_independent_reader_decodes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import relloc.runs.recording as recording
    from relloc.cli import main

    captured: dict[str, Any] = {}
    real = recording.write_mcap

    def spy(path: Path, engine: Any, report: Any, **kw: Any) -> Path:
        captured["estimates"] = list(engine.pipelines[0].estimates)
        captured["distro"] = kw["distro"]
        return real(path, engine, report, **kw)

    monkeypatch.setattr(recording, "write_mcap", spy)
    json_path, mcap_path, out = tmp_path / "run.json", tmp_path / "run.mcap", tmp_path / "out"
    args = [
        "run",
        "multi",
        "--methods",
        "pf",
        "--particles",
        "500",
        "--no-progress",
        "--span",
        ":15",
    ]
    assert main([*args, "--json", str(json_path), "--out", str(out), "--mcap", str(mcap_path)]) == 0
    assert mcap_path.is_file()
    topics = read_mcap(mcap_path)
    estimates: list[Estimate] = captured["estimates"]
    figures = json.loads(json_path.read_text())["scenarios"]
    (scenario,) = figures.values()
    assert scenario["methods"]["pf"]["n_estimates"] == len(estimates) > 0
    robots = sorted(estimates[-1].positions)
    reference = estimates[-1].reference

    poses = {t: m for t, m in topics.items() if t.startswith("/relloc/pf/") and t.endswith("/pose")}
    assert sorted(poses) == [f"/relloc/pf/{r}/pose" for r in robots]
    for robot in robots:
        mine = [e.published() for e in estimates if robot in e.positions]  # what is published
        got = poses[f"/relloc/pf/{robot}/pose"]
        assert len(got) == len(mine)
        for (schema, log_time, msg), est in zip(got, mine, strict=True):
            assert schema == "geometry_msgs/msg/PoseWithCovarianceStamped"
            assert log_time == round(est.t * 1e9)
            assert msg.header.frame_id == est.frame_id
            stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            assert stamp == pytest.approx(est.t, abs=1e-9)
            pos = msg.pose.pose.position
            assert (pos.x, pos.y, pos.z) == (*est.positions[robot], 0.0)
            cov = np.array(msg.pose.covariance).reshape(6, 6)
            np.testing.assert_array_equal(cov[:2, :2], np.array(est.covariances[robot]))
            assert np.all(np.diag(cov)[2:] == NOT_ESTIMATED)  # z, roll, pitch; no heading: yaw
        # the positions are the TUM file's too (written by another path of the run)
        tum = np.loadtxt(out / "tum" / f"pf_{robot}.txt")
        assert len(tum) > 0
        by_time = {round(e.t, 6): e.positions[robot] for e in mine}
        for row in tum:
            np.testing.assert_allclose(by_time[round(row[0], 6)], row[1:3], atol=1e-6)

    status = topics["/relloc/pf/status"]
    assert len(status) == len(estimates)
    for (schema, _, msg), est in zip(status, estimates, strict=True):
        assert schema == "diagnostic_msgs/msg/DiagnosticArray"
        (s,) = msg.status
        assert s.message == est.status
        assert s.level == (0 if est.status == "ok" else 1)
        values = {kv.key: kv.value for kv in s.values}
        assert values == {
            "orientation_observable": str(est.orientation_observable).lower(),
            "inconsistent": str(est.inconsistent).lower(),
            "recovering": str(est.recovering).lower(),
        }
    assert any(s[2].status[0].level == 1 for s in status)  # unobservable at the start

    for robot in robots:
        truth = topics[f"/relloc/truth/{robot}/pose"]
        assert 0 < len(truth) <= len(estimates)
        assert {m.header.frame_id for _, _, m in truth} == {reference}
        assert all(schema == "geometry_msgs/msg/PoseStamped" for schema, _, _ in truth)
        gt = np.loadtxt(out / "tum" / f"groundtruth_{robot}.txt")  # the evaluation's pairs
        got = np.array([(lt * 1e-9, m.pose.position.x, m.pose.position.y) for _, lt, m in truth])
        np.testing.assert_allclose(got, gt[:, :3], atol=2e-6)

    ranges = [t for t in topics if t.startswith("/relloc/ranges/")]
    assert ranges and all(topics[t][0][0] == "sensor_msgs/msg/Range" for t in ranges)
    assert captured["distro"] == "jazzy"
    assert all(hasattr(m, "variance") for t in ranges for _, _, m in topics[t])  # jazzy's layout


def test_headings_body_frame_and_older_distro(tmp_path: Path) -> None:
    """Yaw variance from the heading estimate, the body frame's id, and humble's layouts."""
    from relloc.events import RangeEvent
    from relloc.sinks.mcap import write_mcap

    est = Estimate(
        t=2.5, method="pf", reference="r0", positions={"r1": (1.0, -2.0)},
        covariances={"r1": ((0.04, 0.01), (0.01, 0.09))}, headings={"r1": (0.3, 0.2)},
        frame=BODY_FRAME, recovering=True,
    )  # fmt: skip
    engine = SimpleNamespace(pipelines=[SimpleNamespace(name="pf", estimates=[est])])
    ranges = [RangeEvent(t=2.4, robot_a="r0", robot_b="r1", distance=2.2)]
    path = write_mcap(tmp_path / "sub" / "h.mcap", engine, None, distro="humble", ranges=ranges)  # type: ignore[arg-type]
    topics = read_mcap(path)
    assert sorted(topics) == ["/relloc/pf/r1/pose", "/relloc/pf/status", "/relloc/ranges/r0/r1"]
    ((_, _, pose),) = topics["/relloc/pf/r1/pose"]
    assert pose.header.frame_id == "r0/base_link"
    cov = np.array(pose.pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(cov[:2, :2], [[0.04, 0.01], [0.01, 0.09]])
    assert cov[5, 5] == pytest.approx(0.04)
    ((_, _, status),) = topics["/relloc/pf/status"]
    assert status.status[0].level == 1 and status.status[0].message.startswith("recovering")
    ((_, log_time, rng),) = topics["/relloc/ranges/r0/r1"]
    assert log_time == 2_400_000_000 and rng.range == pytest.approx(2.2)
    assert not hasattr(rng, "variance")  # humble's Range has none
    assert list(tmp_path.joinpath("sub").iterdir()) == [path]  # no rosbag2 folder left behind
