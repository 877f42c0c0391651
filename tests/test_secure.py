"""Authenticated, authorised Zenoh (``relloc secure init``, ``--secure DIR``) on loopback.

Every session is a peer on 127.0.0.1 with mutual TLS (``tls/`` endpoints on free ports,
multicast scouting off) and the team's access control. A refusal is shown by a positive
control: a message the rules allow, sent after the refused ones on the same links, has
arrived, and the refused ones have not.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
from test_navigation_live import SMALL, check_small_rectangle, relloc, stop, write_team
from waiting import wait_until

from relloc.config import TeamConfig
from relloc.events import OdometryEvent, RangeEvent
from relloc.live import (
    EstimateCollector,
    LiveServer,
    ServeOptions,
    ZenohOptions,
    free_tcp_port,
    open_session,
    publish_events,
    simulated_team,
)
from relloc.live.secure.access import grants, roles
from relloc.live.secure.certificates import SecureDirError, write_secure_dir
from relloc.live.secure.identity import security_of
from relloc.live.secure.refusals import AccessRefusals
from relloc.navigation.live import decode_estimate
from relloc.ros.messages import (
    TWIST,
    decode,
    encode,
    odometry_msg,
    pose_with_covariance_msg,
    range_msg,
    twist_msg,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def team(tmp_path_factory: pytest.TempPathFactory) -> tuple[TeamConfig, Path]:
    """The simulated five-robot team and its secure directory (written once: EC keys are fast,
    but every test needs the same CA)."""
    _, config = simulated_team(seed=0, duration=16.0)
    out = tmp_path_factory.mktemp("secure") / "team"
    write_secure_dir(config, out)
    return config, out


def tls(port: int) -> str:
    return f"tls/127.0.0.1:{port}"


def open_role(
    folder: Path, role: str, *, listen: int | None = None, connect: tuple[int, ...] = ()
) -> Any:
    """A session with ``folder/<role>.json5``."""
    return open_session(
        ZenohOptions(
            config_file=folder / f"{role}.json5",
            listen=(tls(listen),) if listen is not None else (),
            connect=tuple(tls(p) for p in connect),
            multicast=False,
        )
    )


# ============================================================================ relloc secure init
def test_secure_init_writes_a_ca_a_certificate_and_a_config_per_role(tmp_path: Path) -> None:
    from cryptography import x509
    from cryptography.x509.oid import ExtensionOID, NameOID

    team = REPO / "configs" / "tiers" / "multi4_shortbag_20221011.toml"
    out = tmp_path / "sec"
    args = [
        sys.executable,
        "-m",
        "relloc.cli",
        "secure",
        "init",
        "--config",
        str(team),
        "--out",
        str(out),
    ]
    done = subprocess.run(
        [*args, "--host", "robot1.lan", "--host", "10.0.0.7"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    config = TeamConfig.load(team)
    assert roles(config) == [
        "serve",
        "navigate",
        "team",
        *(f"robot-{r}" for r in config.robot_names),
    ]
    ca = x509.load_pem_x509_certificate((out / "ca.pem").read_bytes())
    for role in roles(config):
        cert = x509.load_pem_x509_certificate((out / f"{role}.pem").read_bytes())
        cert.verify_directly_issued_by(ca)
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == role
        names = cert.extensions.get_extension_for_oid(ExtensionOID.SUBJECT_ALTERNATIVE_NAME).value
        assert [str(n.value) for n in names] == ["localhost", "127.0.0.1", "robot1.lan", "10.0.0.7"]
        assert stat.S_IMODE(os.stat(out / f"{role}.json5").st_mode) == 0o600
        text = (out / f"{role}.json5").read_text()
        assert text.startswith("// relloc secure init") and "PRIVATE KEY" not in text  # base64
    assert stat.S_IMODE(os.stat(out / "ca.key").st_mode) == 0o600
    assert stat.S_IMODE(os.stat(out).st_mode) == 0o700
    # An existing directory is never overwritten without --force.
    before = (out / "ca.pem").read_bytes()
    again = subprocess.run(args, capture_output=True, text=True, cwd=REPO, timeout=60)
    assert again.returncode == 2 and "--force" in again.stderr
    assert (out / "ca.pem").read_bytes() == before
    with pytest.raises(SecureDirError):
        write_secure_dir(config, out)
    write_secure_dir(config, out, force=True)
    assert (out / "ca.pem").read_bytes() != before


def test_the_rules_are_derived_from_the_team_config(team: tuple[TeamConfig, Path]) -> None:
    config, folder = team
    g = grants(config)
    assert g["serve"] == ["relloc/**"]
    assert g["navigate"] == ["r1/cmd_vel", "r2/cmd_vel", "r3/cmd_vel", "r4/cmd_vel"]
    assert g["robot-r1"] == [
        "r1/odom",
        "uwb/tof/n_1/n_0/distance",
        "uwb/tof/n_1/n_2/distance",
        "uwb/tof/n_1/n_3/distance",
        "uwb/tof/n_1/n_4/distance",
    ]
    assert set(g["team"]) == {k for r in config.robot_names for k in g[f"robot-{r}"]} | {
        f"vrpn_client_node/{r}/pose" for r in config.robot_names
    }
    from relloc.ros.interfaces import RosInterface

    rmw = grants(config, RosInterface("rmw_zenoh", 7))
    assert rmw["serve"] == ["7/relloc/**"] and rmw["robot-r1"][0] == "7/r1/odom/*/*"
    # The files say so: every role's config holds the same rules, and its own identity.
    import zenoh

    for role in ("serve", "robot-r1"):
        conf = zenoh.Config.from_file(str(folder / f"{role}.json5"))
        acl = json.loads(conf.get_json("access_control"))
        assert acl["enabled"] and acl["default_permission"] == "deny"
        rule = next(r for r in acl["rules"] if r["id"] == "put-robot-r1")
        assert rule["key_exprs"] == g["robot-r1"] and rule["flows"] == ["ingress"]
        conf.insert_json5("listen/endpoints", json.dumps([tls(7447)]))
        sec = security_of(conf, folder / f"{role}.json5")
        assert sec.authenticated and sec.identity == role and sec.access_control
    assert not security_of(zenoh.Config()).authenticated


def test_refusals_are_counted_from_zenohs_trace_log() -> None:
    """Zenoh's own lines (colours and all): a refused message is counted; a key refused while
    its permissions are cached is listed apart; the rest is not the access control's."""
    head = "\x1b[2m2026-01-01T00:00:00Z\x1b[0m \x1b[35mTRACE\x1b[0m  rx-0 ThreadId(07) zenoh::net::routing::interceptor::access_control: "
    link = "ab on Interface(lo)+CertCommonName({cn})+Transport(Tls)+ab is {verdict} to {msg} ({flow}) on {key}"
    refusals = AccessRefusals()
    lines = [
        head + "ACL (ingress): caching permissions for `r2/cmd_vel` ...",
        head
        + link.format(
            cn="team", verdict="authorized", msg="Query", flow="ingress", key="r2/cmd_vel"
        ),
        head
        + link.format(
            cn="team", verdict="unauthorized", msg="Put", flow="ingress", key="r2/cmd_vel"
        ),
        head
        + link.format(
            cn="robot-r1", verdict="unauthorized", msg="Put", flow="ingress", key="r2/odom"
        ),
        head
        + link.format(
            cn="robot-r1", verdict="unauthorized", msg="Put", flow="ingress", key="r2/odom"
        ),
        head
        + link.format(
            cn="serve", verdict="authorized", msg="Put", flow="egress", key="relloc/r2/pose"
        ),
    ]
    assert all(refusals.feed(line) for line in lines)
    assert not refusals.feed("relloc serve: sim_nav, pf, 4000 particles")
    assert refusals.as_dict() == {
        "messages": {"robot-r1 put ingress r2/odom": 2},
        "in_advance": ["team put ingress r2/cmd_vel"],
    }
    assert refusals.total == 2


# ============================================================================ who may connect
def test_a_session_without_a_certificate_of_the_teams_ca_cannot_connect(
    team: tuple[TeamConfig, Path], tmp_path: Path
) -> None:
    config, folder = team
    other = tmp_path / "other"
    write_secure_dir(config, other)  # the same roles, another CA
    port = free_tcp_port()
    serve = open_role(folder, "serve", listen=port)
    got: list[bytes] = []
    sub = serve.declare_subscriber("r1/odom", lambda s: got.append(s.payload.to_bytes()))
    ca_only = json.dumps(
        {"mode": "peer", "scouting": {"multicast": {"enabled": False}}, "connect": {"endpoints": [tls(port)]},
         "transport": {"link": {"tls": {"root_ca_certificate": str(folder / "ca.pem")}}}}
    )  # fmt: skip
    import zenoh

    intruders = {
        "plain TCP": open_session(
            ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), multicast=False)
        ),
        "another CA": open_role(other, "robot-r1", connect=(port,)),
        "no certificate": zenoh.open(zenoh.Config.from_json5(ca_only)),
    }
    robot = open_role(folder, "robot-r1", connect=(port,))
    try:
        for name, s in intruders.items():
            s.put("r1/odom", name.encode())
        assert wait_until(lambda: len(robot.info.links()) == 1, timeout=10)
        robot.put("r1/odom", b"robot-r1")
        assert wait_until(lambda: b"robot-r1" in got, timeout=10)
        for s in intruders.values():
            s.put("r1/odom", b"again")
        robot.put("r1/odom", b"robot-r1 again")
        assert wait_until(lambda: b"robot-r1 again" in got, timeout=10)
        assert got == [b"robot-r1", b"robot-r1 again"]
        assert {name: s.info.links() for name, s in intruders.items()} == {
            name: [] for name in intruders
        }
        assert [link.auth_identifier for link in serve.info.links()] == ["robot-r1"]
    finally:
        sub.undeclare()
        for s in [*intruders.values(), robot, serve]:
            s.close()


# ============================================================================ who may speak
class Attacker:
    """Robot r1's certificate, publishing what only others may: r2's odometry and ranges, a
    pose on ``relloc/r2/pose``, r2's ``cmd_vel`` (undeclared puts and a declared publisher)."""

    def __init__(self, session: Any, base: float) -> None:
        self.session = session
        self.base = base
        self.sent = 0
        self.halt = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.cmd_pub = session.declare_publisher("r2/cmd_vel")

    def _run(self) -> None:
        t = 0.0
        while not self.halt.is_set():
            t += 0.05
            s = self.session
            s.put(
                "r2/odom", encode(odometry_msg(OdometryEvent(self.base + t, "r2", 5.0, 5.0, 0.0)))
            )
            s.put(
                "uwb/tof/n_2/n_0/distance",
                encode(range_msg(RangeEvent(self.base + t, "r2", "r0", 9.0, "n_2", "n_0"))),
            )
            cov = [[1e-4, 0.0], [0.0, 1e-4]]
            s.put(
                "relloc/r2/pose",
                encode(pose_with_covariance_msg(self.base + t, 9.0, 9.0, cov=cov, frame_id="r0")),
            )
            s.put("r2/cmd_vel", encode(twist_msg(1.0, 1.0)))
            self.cmd_pub.put(encode(twist_msg(1.0, 1.0)))
            self.sent += 1
            self.halt.wait(0.02)

    def __enter__(self) -> Attacker:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.halt.set()
        self.thread.join(timeout=5)
        self.cmd_pub.undeclare()


def _serve_simulated_team(folder: Path, attack: bool) -> tuple[list[Any], dict[str, Any]]:
    """The simulated team (``team``) into an in-process server (``serve``) over mutual TLS,
    a ``navigate`` session listening to the poses and the robots' ``cmd_vel``, and with
    ``attack`` robot r1's certificate publishing what it may not. Returns the server's
    estimates and what reached whom."""
    sim, config = simulated_team(seed=0, duration=16.0)
    p_serve, p_team = free_tcp_port(), free_tcp_port()
    serve = open_role(folder, "serve", listen=p_serve)
    team = open_role(folder, "team", listen=p_team, connect=(p_serve,))
    nav = open_role(folder, "navigate", connect=(p_serve, p_team))
    sessions = [nav, team, serve]
    seen: dict[str, Any] = {"cmd_vel": [], "poses": []}
    subs = [
        team.declare_subscriber("r2/cmd_vel", lambda s: seen["cmd_vel"].append(decode(s.payload.to_bytes(), TWIST).linear.x)),
        nav.declare_subscriber("relloc/r2/pose", lambda s: seen["poses"].append(decode_estimate(s.payload.to_bytes(), "r2", "r0").positions["r2"])),
    ]  # fmt: skip
    rate = 4.0
    base = 1_700_000_000.0
    server = LiveServer(
        config, serve, ServeOptions(particles=1000, clock_rate=rate, reorder_window=2.0)
    )
    attacker = None
    try:
        assert wait_until(
            lambda: len(serve.info.links()) == 2 and len(nav.info.links()) == 2, timeout=10
        )
        if attack:
            attacker_session = open_role(folder, "robot-r1", connect=(p_serve, p_team))
            sessions.insert(0, attacker_session)
            assert wait_until(lambda: len(attacker_session.info.links()) == 2, timeout=10)
            attacker = Attacker(attacker_session, base).__enter__()
        collector = EstimateCollector(nav, config)
        server.start()
        runner = threading.Thread(target=server.run, daemon=True)
        runner.start()
        stats = publish_events(sim.events(), config, team, rate=rate, time_base=base, wait=5.0)
        assert stats.unmatched == []
        assert wait_until(lambda: server.source.stats.events.total() >= stats.messages, timeout=20)
        # The navigator's own command, after the attacker's: it arrives, theirs did not.
        nav.put("r2/cmd_vel", encode(twist_msg(0.25, 0.0)))
        assert wait_until(lambda: 0.25 in seen["cmd_vel"], timeout=10)
        server.stop()
        runner.join(timeout=20)
        own = server.pipelines[0].estimates
        assert wait_until(lambda: len(collector.estimates()) >= len(own), timeout=20)
        collector.close()
        seen["sent"] = attacker.sent if attacker else 0
        seen["messages"] = dict(server.source.stats.messages)
        return list(own), seen
    finally:
        if attacker is not None:
            attacker.__exit__()
        server.close()
        for sub in subs:
            sub.undeclare()
        for s in sessions:
            s.close()


def test_a_robot_publishing_what_is_not_its_own_is_refused(team: tuple[TeamConfig, Path]) -> None:
    """Robot r1's certificate publishing r2's odometry and ranges, a pose on relloc/r2/pose and
    r2's cmd_vel: the server's estimates are bit-identical to the run without it, the
    navigator sees only the server's poses, and r2's cmd_vel carries only the navigator's."""
    _, folder = team
    clean, clean_seen = _serve_simulated_team(folder, attack=False)
    attacked, seen = _serve_simulated_team(folder, attack=True)
    assert seen["sent"] > 50
    print(f"attacker sent {seen['sent']} rounds of 5 messages; {len(attacked)} estimates")
    assert seen["messages"] == clean_seen["messages"]
    assert len(attacked) == len(clean) > 100
    for a, b in zip(attacked, clean, strict=True):
        assert a.t == b.t and a.positions == b.positions and a.covariances == b.covariances
    assert seen["cmd_vel"] == [0.25] and clean_seen["cmd_vel"] == [0.25]
    assert len(seen["poses"]) == len(clean_seen["poses"]) and (9.0, 9.0) not in seen["poses"]


# ============================================================================ the whole system
@pytest.mark.slow
def test_secure_sim_robots_serve_and_navigate_drive_the_small_rectangle_under_attack(
    team: tuple[TeamConfig, Path], tmp_path: Path
) -> None:
    """sim-robots, serve and navigate as processes over mutual TLS (a full mesh: serve and
    sim-robots listen, navigate connects to both and listens), robot r1's certificate attacking all along:
    the path is completed as over plain TCP, the refusals are counted by serve and navigate."""
    team_toml = write_team(tmp_path)
    config = TeamConfig.load(team_toml)
    folder = tmp_path / "sec"
    write_secure_dir(config, folder)
    p_sim, p_serve, p_nav = free_tcp_port(), free_tcp_port(), free_tcp_port()
    sec = ["--no-multicast", "--secure", str(folder)]
    procs = []
    attacker_session = None
    try:
        procs.append(relloc("sim-robots", "--scenario", "nav", "--config", str(team_toml), "--rate", "2", "--duration", "120",
                            "--json", str(tmp_path / "sim.json"), *sec, "--listen", tls(p_sim), log=tmp_path / "sim.log"))  # fmt: skip
        procs.append(relloc("serve", "--config", str(team_toml), "--clock-rate", "2", "--reorder-window", "0.1",
                            "--json", str(tmp_path / "serve.json"),
                            *sec, "--listen", tls(p_serve), "--connect", tls(p_sim), log=tmp_path / "serve.log"))  # fmt: skip
        nav = relloc("navigate", "--config", str(team_toml), "--robot", "r2", "--path", str(SMALL), "--clock-rate", "2",
                     "--duration", "50", "--json", str(tmp_path / "nav.json"), *sec, "--connect", tls(p_sim),
                     "--connect", tls(p_serve), "--listen", tls(p_nav), log=tmp_path / "nav.log")  # fmt: skip
        procs.append(nav)
        attacker_session = open_role(folder, "robot-r1", connect=(p_sim, p_serve, p_nav))
        with Attacker(attacker_session, 0.0) as attacker:
            try:
                code = nav.wait(timeout=75)
            except subprocess.TimeoutExpired:
                code = None
        logs = "\n".join(f"--- {p.name}\n{p.read_text()}" for p in tmp_path.glob("*.log"))
        assert code == 0, logs
    finally:
        for proc in reversed(procs):
            stop(proc)
        if attacker_session is not None:
            attacker_session.close()
    summary = json.loads((tmp_path / "nav.json").read_text())
    truth = json.loads((tmp_path / "sim.json").read_text())
    check_small_rectangle(summary, truth)
    assert summary["received"]["unverified"] == 0
    # r2 obeyed the navigator alone: none of the attacker's commands reached the robots.
    assert truth["commands_received"] <= summary["commands_sent"]
    logs = {p.stem: p.read_text() for p in tmp_path.glob("*.log")}
    assert "zenoh session authenticated as 'serve' (mutual TLS" in logs["serve"]
    assert "authenticated as 'navigate'" in logs["nav"] and "poses only from 'serve'" in logs["nav"]

    # Zenoh reports a refused key once when it caches the sender's permissions for it, or per
    # message while it judges them one by one: each attack is reported, at least once.
    def reported(refused: dict[str, Any]) -> set[str]:
        return {*refused["messages"], *refused["in_advance"]}

    serve_refused = reported(json.loads((tmp_path / "serve.json").read_text())["access_refused"])
    nav_refused = reported(summary["access_refused"])
    print(f"attacker sent {attacker.sent} rounds; serve reports {len(serve_refused)} refusals")
    # Each is reported where it is subscribed to: r2's data at serve, the pose at navigate.
    for key in ("r2/odom", "uwb/tof/n_2/n_0/distance"):
        assert f"robot-r1 put ingress {key}" in serve_refused
    assert "robot-r1 put ingress relloc/r2/pose" in nav_refused


# ============================================================================ navigate's poses
class _Sample:
    """What ``LiveNavigation`` reads of a Zenoh sample: its payload."""

    def __init__(self, payload: bytes) -> None:
        self.payload = self
        self._bytes = payload

    def to_bytes(self) -> bytes:
        return self._bytes


def test_navigate_acts_only_on_poses_it_can_tell_come_from_serve(
    team: tuple[TeamConfig, Path],
) -> None:
    """With ``pose_identity`` a pose is used only while a link authenticated as serve is up;
    otherwise the robot is held (``unverified``) at the next control step."""
    from relloc.navigation.live import LiveNavigation, NavigateOptions
    from relloc.navigation.path import load_path

    config, folder = team
    x0, y0 = load_path(SMALL).waypoints[0]
    pose = _Sample(
        encode(
            pose_with_covariance_msg(100.0, x0, y0, cov=[[1e-3, 0.0], [0.0, 1e-3]], frame_id="r0")
        )
    )
    opts = NavigateOptions(robot="r2", path=load_path(SMALL), pose_identity="serve")
    port = free_tcp_port()
    nav_session = open_role(folder, "navigate", listen=port)
    live = LiveNavigation(config, nav_session, opts)
    robot = open_role(folder, "robot-r1", connect=(port,))  # authenticated, but not serve
    try:
        assert wait_until(lambda: len(nav_session.info.links()) == 1, timeout=10)
        live._on_pose(pose)
        assert live.received == {"odometry": 0, "estimate": 0, "decode_error": 0, "unverified": 1}
        assert live.navigator.gate.check(100.0, None, None) == (
            "unverified",
            "no link authenticated as 'serve'",
        )
        cmd = live.navigator.update(100.0)
        assert (cmd.v, cmd.w) == (0.0, 0.0) and live.navigator.gate.reason == "unverified"
        serve = open_role(folder, "serve", connect=(port,))
        try:
            assert wait_until(lambda: len(nav_session.info.links()) == 2, timeout=10)
            live._on_pose(pose)
            assert live.received["estimate"] == 1 and live.navigator.gate.untrusted is None
            assert live.navigator.estimate is not None and live.navigator.estimate.t == 100.0
        finally:
            serve.close()
    finally:
        live.close()
        robot.close()
        nav_session.close()


@pytest.mark.slow
@pytest.mark.shared_data
def test_the_shortbag_replayed_into_a_secure_serve_gives_the_plain_runs_ape(
    shared_data: Path, team: tuple[TeamConfig, Path], tmp_path: Path
) -> None:
    """``replay`` (``team``) into a server (``serve``) over mutual TLS with the access control:
    the APE of ``relloc run`` on the same bag, particles and seed, as over plain TCP
    (``test_zenoh_live.test_replayed_shortbag_matches_relloc_run``, the same bounds)."""
    from test_zenoh_live import SHORTBAG, _offline_shortbag, serve_replayed

    from relloc.live import ape_against_bag

    bag = shared_data / "tiers" / SHORTBAG
    config = TeamConfig.load(REPO / "configs" / "tiers" / f"{SHORTBAG}.toml")
    folder = tmp_path / "sec"
    write_secure_dir(config, folder)
    particles, seed, rate = 4000, 0, 2.0
    offline = _offline_shortbag(bag, particles, seed)
    port = free_tcp_port()
    serve = open_role(folder, "serve", listen=port)
    client = open_role(folder, "team", connect=(port,))
    try:
        assert wait_until(lambda: len(serve.info.links()) == 1, timeout=10)
        estimates, stats, server = serve_replayed(bag, config, serve, client, particles, seed, rate)
    finally:
        client.close()
        serve.close()
    pf = offline.methods["pf"]
    served = ape_against_bag(estimates, bag, config, warmup=offline.warmup, t0=offline.t0)
    print(
        f"secure: served mean APE median {served['mean_median']:.3f} m over {len(estimates)} "
        f"estimates; relloc run {pf.mean_ape_median:.3f} m over {pf.n_estimates}; "
        f"{server.source.stats.out_of_order} events out of order"
    )
    assert server.source.stats.out_of_order == 0
    assert abs(len(estimates) - pf.n_estimates) <= 2
    assert served["mean_median"] == pytest.approx(pf.mean_ape_median, rel=0.10), (
        f"the replay fell behind by up to {stats.max_behind_s:.3f} s (restamped odometry)"
    )
