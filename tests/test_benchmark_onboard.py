"""benchmarks/onboard.py: its relay cuts and heals a link; a tiny team of onboard serve processes
with one robot partitioned writes the figures, and the partition really held."""

from __future__ import annotations

import json
import socket
import threading
from pathlib import Path

import pytest
from load_file import ROOT, load_module
from waiting import wait_until

bench = load_module(ROOT / "benchmarks" / "onboard.py", "bench_onboard")


def test_the_relay_forwards_and_a_cut_closes_and_refuses_until_healed() -> None:
    upstream = socket.create_server(("127.0.0.1", 0))
    conns: list[socket.socket] = []
    threading.Thread(
        target=lambda: [conns.append(upstream.accept()[0]) for _ in range(2)], daemon=True
    ).start()
    relay = bench.Relay(upstream.getsockname()[1])
    try:
        client = socket.create_connection(("127.0.0.1", relay.port))
        assert wait_until(lambda: len(conns) == 1, 5.0)
        client.sendall(b"ping")
        assert conns[0].recv(16) == b"ping"
        relay.cut()
        client.settimeout(5.0)
        assert client.recv(16) == b""  # the link dropped
        refused = socket.create_connection(("127.0.0.1", relay.port))
        refused.settimeout(5.0)
        assert refused.recv(16) == b""
        assert wait_until(lambda: relay.refused == 1, 5.0)
        relay.heal()
        again = socket.create_connection(("127.0.0.1", relay.port))
        assert wait_until(lambda: len(conns) == 2, 5.0)
        again.sendall(b"pong")
        assert conns[1].recv(16) == b"pong"
        # the relay counts a chunk once it has forwarded it: wait for the count, not only the data
        assert len(relay.accepted) == 2 and wait_until(lambda: relay.bytes == 8, 5.0)
    finally:
        relay.close()
        upstream.close()


def test_bad_partitions_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench.main(["--partition", "r1:5:2"]) == 2
    assert bench.main(["--duration", "10", "--partition", "r1:5:10"]) == 2
    assert "END" in capsys.readouterr().err


def test_own_messages_in_flight_are_not_counted_as_heard_from_others() -> None:
    """The cut robot's foreign messages: both counts of a status come from its source, so one
    of its own messages published but not yet received (under load) never counts as -1."""

    class Sink:
        def publish_status(self, status: dict[str, object]) -> None:
            pass

    received = {"r1/odom": 10, "uwb/r1/r2": 4}
    own_keys = {"r1/odom", "uwb/r1/r2"}
    tap = bench._Tap(Sink(), [0.0], lambda: dict(received), own_keys)
    status = {"time": 10.0, "hears": ["r1", "r2"], "source": {"messages": 14}}
    tap.publish_status(status)
    own_keys.add("r1/cmd")  # a key published on, its message still on its way
    received["r1/odom"] += 1
    tap.publish_status(status | {"time": 11.0, "source": {"messages": 15}})
    result = {"partition": {"cut_at_s": 5.0, "healed_at_s": 20.0}}
    bench._partition_checks(
        result, {"r1": {"statuses": tap.statuses}}, bench.Partition("r1", 5.0, 20.0), 0.0
    )
    assert result["partition"]["cut_robot_foreign_messages_during"] == 0
    received["r0/odom"] = 1  # one message from another robot
    tap.publish_status(status | {"time": 12.0, "source": {"messages": 16}})
    bench._partition_checks(
        result, {"r1": {"statuses": tap.statuses}}, bench.Partition("r1", 5.0, 20.0), 0.0
    )
    assert result["partition"]["cut_robot_foreign_messages_during"] == 1


def test_the_serves_filter_kind_and_reorder_window_are_options() -> None:
    _, config = bench.team(3, 0, 5.0, "smoother")
    assert config.filter.kind == "smoother"
    assert bench.team(3, 0, 5.0)[1].filter.kind == "auto"  # the config's own
    args = bench._parser().parse_args(["--kind", "smoother", "--reorder-window", "0.3"])
    assert (args.kind, args.reorder_window) == ("smoother", 0.3)
    out = {"views": {"r0": {}}, "cpu_percent": {}, "bare_cpu_percent": None}
    out |= {"publisher_cpu_percent": {}, "rss_mb": {}, "rss_anon_mb": {}, "rss_file_mb": {}}
    assert bench._line(out).startswith("views: none in a body frame")


def test_three_onboard_serves_one_cut_off(tmp_path: Path) -> None:
    out = tmp_path / "onboard.json"
    assert bench.main(["--robots", "3", "--duration", "9", "--settle", "2",
                       "--partition", "r1:2:6", "--floor", "--json", str(out)]) == 0  # fmt: skip
    d = json.loads(out.read_text())
    robots = {"r0", "r1", "r2"}
    assert set(d["views"]) == robots
    for me, views in d["views"].items():
        assert set(views) == robots - {me}
        for v in views.values():
            assert v["n"] > 0 and v["ape_median"] < 1.0 and 0.0 <= v["coverage95"] <= 1.0
    for key in ("cpu_percent", "publisher_cpu_percent", "rss_mb", "rss_anon_mb", "rss_file_mb",
                "formation_skipped", "views_partitioned"):  # fmt: skip
        assert set(d[key]) == robots, key
    assert d["bare_cpu_percent"] is not None and all(v > 0 for v in d["rss_mb"].values())
    for me in robots:  # the serve alone: the process less its robot's publisher thread
        serve = d["cpu_percent"][me] - d["publisher_cpu_percent"][me]
        assert d["serve_cpu_ratio"][me] == pytest.approx(serve / d["bare_cpu_percent"], abs=0.01)
        assert d["serve_cpu_ratio"][me] <= d["cpu_ratio"][me]
    p = d["partition"]
    assert p["robot"] == "r1" and p["relay_bytes_during"] == 0 and p["statuses_during"] >= 2
    # nothing from the others reached r1 while cut: it hears only itself and r2, whom the
    # ranges its own node measures name
    assert p["cut_robot_foreign_messages_during"] == 0
    assert "r0" not in p["hears_during"]["r1"]
    assert p["rejoined_after_s"] is not None and p["rejoined_after_s"] < 2.0
    assert d["partition_shift"]["n"] > 0 and d["partition_shift_m"] is not None
    assert d["partition_shift_floor"]["n"] > 0 and d["partition_shift_floor_m"] >= 0.0
    assert "recovery_s" in d and "recovery" in d
    # the recovery test on the run without the partition: a number of seconds, or why not
    floor = d["recovery_floor"]
    assert d["recovery_floor_s"] == floor["recovery_s"]
    assert floor["recovery_s"] is not None or floor["why"]
