"""rmw_zenoh without ROS: type hashes, keys, attachments, liveliness tokens, and the live engine.

The expected values are ROS 2's own, quoted where they were published:

* ros2/rmw_zenoh ``docs/design.md`` (section "Topic and Service name mapping to Zenoh key
  expressions" and "Graph Cache"): the ``chatter`` key
  ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74...1a18`` and the ``talker``/``listener``
  liveliness tokens; the attachment layout (section "Publishers").
* the C code rosidl generates for ROS 2 messages (``rosidl_generator_c``, the
  ``<type>__EXPECTED_HASH`` constants of ``*__description.c`` in public ROS 2 build trees,
  e.g. ``nav_msgs__msg__Odometry__EXPECTED_HASH = {1, {0x3c, 0xc9, 0x7d, 0xc7, ...}}``,
  ``geometry_msgs__msg__Twist__EXPECTED_HASH = {1, {0x9c, 0x45, 0xbf, 0x16, ...}}``), written
  below as the RIHS01 strings they are.

The network tests open peer sessions on 127.0.0.1 with a free port and multicast scouting off,
and close them.
"""

from __future__ import annotations

import struct
import threading
import time
from typing import Any

import pytest
from waiting import wait_until

from relloc.events import OdometryEvent
from relloc.live import (
    EstimateCollector,
    LiveServer,
    ServeOptions,
    publish_events,
    simulated_team,
)
from relloc.ros.interfaces import (
    RMW_ZENOH,
    RmwAttachment,
    RosInterface,
    dds_type_name,
    ros_type_name,
)
from relloc.ros.messages import (
    ODOMETRY,
    POSE_WITH_COVARIANCE_STAMPED,
    decode,
    encode,
    odometry_msg,
    typestore,
)
from relloc.ros.type_hash import type_hash
from relloc.sources.zenoh_source import ZenohSource, ZenohSourceOptions

RMW = RosInterface(RMW_ZENOH, 0)
T0 = 1_700_000_000.0

PUBLISHED_HASHES = {
    # rmw_zenoh docs/design.md, the chatter topic of demo_nodes_cpp
    "std_msgs/msg/String": "df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    # rosidl_generator_c *__description.c, <type>__EXPECTED_HASH
    "geometry_msgs/msg/Twist": "9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a",
    "nav_msgs/msg/Odometry": "3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "geometry_msgs/msg/PoseWithCovarianceStamped":
        "26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
    "geometry_msgs/msg/PoseWithCovariance":
        "9a7c0fd234b7f45c6098745ecccd773ca1085670e641071353 97aee31c02e1bb".replace(" ", ""),
    "geometry_msgs/msg/TwistWithCovariance":
        "49f574f033f095d8b6cd1beaca5ca7925e296e84af1716d16c89d38b059c8c18",
    "geometry_msgs/msg/Pose": "d501954e9476cea2996984e812054b68026ae0bfae789d9a10b23daf35cc90fa",
    "geometry_msgs/msg/Quaternion":
        "8a765f66778c8ff7c8ab94afcc590a2ed5325a1d9a076ffff38fbce36f458684",
    "geometry_msgs/msg/Vector3": "cc12fe83e4c02719f1ce8070bfd14aecd40f75a96696a67a2a1f37f7dbb0765d",
    "geometry_msgs/msg/Point": "6963084842a9b04494d6b2941d11444708d892da2f4b09843b9c43f42a7f6881",
    "std_msgs/msg/Header": "f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
    "builtin_interfaces/msg/Time": "b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197",
    # a .msg char is an IDL uint8 (std_msgs__msg__Char__get_type_hash: 0x3a, 0xd2, 0xd0, 0x4d...)
    "std_msgs/msg/Char": "3ad2d04dd29ba19d04b16659afa3ccaedd691914b02a64e82e252f2fa6a586a9",
    # a bounded sequence has its bound as capacity (float64[<=3] dimensions)
    "shape_msgs/msg/SolidPrimitive":
        "2802a15190aadc3f496584df4b0b4c5824d8a0b31aaef839faa75bc34dda38ac",
}  # fmt: skip


@pytest.mark.parametrize("msgtype", sorted(PUBLISHED_HASHES))
def test_type_hashes_are_those_ros2_publishes(msgtype: str) -> None:
    assert type_hash(msgtype) == "RIHS01_" + PUBLISHED_HASHES[msgtype]


HUMBLE_CHAR_TYPES = {
    "std_msgs/msg/Char",
    "rmw_dds_common/msg/Gid",  # char[24] (char[16] since Iron)
    "rmw_dds_common/msg/NodeEntitiesInfo",
    "rmw_dds_common/msg/ParticipantEntitiesInfo",
}


@pytest.mark.parametrize(
    ("distro", "with_char"),
    [
        ("humble", HUMBLE_CHAR_TYPES),
        ("jazzy", {*HUMBLE_CHAR_TYPES, "service_msgs/msg/ServiceEventInfo"}),  # char[16] client_gid
    ],
)
def test_type_hashes_agree_with_rosbags_on_every_type_without_char_fields(
    distro: str, with_char: set[str]
) -> None:
    """An independent implementation (rosbags' ``hash_rihs01``) agrees on the 150-odd other
    types of each distribution's store; it maps ``char`` to FIELD_TYPE_CHAR where rosidl has
    uint8 (see Char above)."""
    store = typestore(distro)
    differ = {t for t in store.fielddefs if type_hash(t, distro) != store.hash_rihs01(t)}
    assert differ == with_char
    assert len(store.fielddefs) - len(differ) > 100


def test_keys_and_liveliness_tokens_follow_the_design_document() -> None:
    string = "std_msgs/msg/String"
    chatter = RosInterface(RMW_ZENOH, 0).channel("chatter", string, scope="robot1")
    assert chatter.key == (
        "0/robot1/chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    )
    assert chatter.topic_key == "0/robot1/chatter" and chatter.name == "/robot1/chatter"
    domain2 = RosInterface(RMW_ZENOH, 2)
    assert domain2.node_token("aac3178e146ba6f1fc6e6a4085e77f21", 0, "listener") == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    )
    talker = domain2.endpoint_token(
        "8b20917502ee955ac4476e0266340d5c", 0, 10, "MP", "talker",
        domain2.channel("/chatter", string), qos="::,7:,:,:,,",
    )  # fmt: skip
    assert talker == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        "std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
    )
    assert dds_type_name(ODOMETRY) == "nav_msgs::msg::dds_::Odometry_"
    assert ros_type_name("nav_msgs::msg::dds_::Odometry_") == ODOMETRY
    assert ros_type_name("Odometry") is None
    # Subscriptions take any type and hash of the topic; the bridge keys are unchanged.
    assert RMW.subscription_expr(RMW.topic_key("/tb1/odom")) == "0/tb1/odom/*/*"
    assert RMW.topic_key("/odom", prefix="lab", scope="tb1") == "lab/0/tb1/odom"
    assert RosInterface().channel("/tb1/odom", ODOMETRY).key == "tb1/odom"
    assert RMW.split_key("0/tb1/odom/T_/RIHS01_x") == ("0/tb1/odom", "T_", "RIHS01_x")


def test_attachment_layout_and_malformed_attachments() -> None:
    gid = bytes(range(16))
    raw = RmwAttachment(7, 1_700_000_000_123_456_789, gid).encode()
    assert len(raw) == 33 and raw[:8] == struct.pack("<q", 7) and raw[16] == 16
    att = RmwAttachment.decode(raw)
    assert (att.sequence, att.gid) == (7, gid) and att.timestamp == pytest.approx(
        1.7e9 + 0.123456789
    )
    for bad in (raw[:-1], raw + b"\x00", raw[:16] + b"\x08" + raw[17:], b""):
        with pytest.raises(ValueError):
            RmwAttachment.decode(bad)
    assert RMW.decode_text(RMW.text_payload('{"a": 1}')) == '{"a": 1}'


def _odom(t: float, robot: str = "r1") -> bytes:
    return encode(odometry_msg(OdometryEvent(t, robot, 1.0, 2.0, 0.0)))


def test_rmw_source_checks_types_and_hashes_and_counts_loss_and_bad_attachments() -> None:
    _, config = simulated_team(seed=0, duration=5.0)
    src = ZenohSource(config, ZenohSourceOptions(interface=RMW))
    channel = RMW.channel("/r1/odom", ODOMETRY)
    assert "0/r1/odom" in src.routes and "0/r1/odom/*/*" in src.expressions
    gid, other = b"\x01" * 16, b"\x02" * 16

    def att(seq: int, g: bytes = gid) -> bytes:
        return RmwAttachment(seq, int((T0 + seq) * 1e9), g).encode()

    src.handle(channel.key, _odom(T0 + 0.00), T0, att(1))
    src.handle(channel.key, _odom(T0 + 0.05), T0, att(2))
    src.handle(channel.key, _odom(T0 + 0.10), T0, att(5))  # 3 and 4 lost
    src.handle(channel.key, _odom(T0 + 0.15), T0, att(1, other))  # another publisher
    foreign = f"0/r1/odom/{dds_type_name(ODOMETRY)}/RIHS01_{'0' * 64}"
    src.handle(foreign, _odom(T0 + 0.20), T0, att(6))  # another hash: counted, decoded
    twist = "0/r1/odom/geometry_msgs::msg::dds_::Twist_/RIHS01_x"  # a type the route does not take
    src.handle(twist, b"x", T0, att(1, b"\x03" * 16))
    src.handle(channel.key, _odom(T0 + 0.25), T0, None)  # no attachment
    src.handle(channel.key, _odom(T0 + 0.30), T0, b"\x00" * 12)  # malformed
    src.handle(channel.key, b"\x00\x01\x00\x00 garbage", T0, att(7))
    arrivals = src.flush()
    assert [a.event.t - T0 for a in arrivals] == pytest.approx(
        [0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3]
    )
    assert [a.sent for a in arrivals[:2]] == pytest.approx([T0 + 1, T0 + 2])
    assert arrivals[-1].sent is None and all(a.key == "0/r1/odom" for a in arrivals)
    assert src.stats.rejected == {"unknown_type": 1, "decode_error": 1}
    assert src.stats.messages == {"0/r1/odom": 8}
    tr = src.transport.as_dict()
    assert tr == {
        "attachment_missing": 1,
        "attachment_malformed": 1,
        "layout_by_hash": 7,
        "hash_not_supported": 0,
        "unknown_type_hash": {f"{dds_type_name(ODOMETRY)}/RIHS01_{'0' * 64}": 1},
        "lost": {"0/r1/odom": 2},
        "sequence_restarts": 0,
        "publishers": 2,
    }


# ---------------------------------------------------------------------------- over Zenoh
def test_served_over_rmw_zenoh_seen_by_a_subscriber_written_from_the_design_document(
    sessions: tuple[Any, Any],
) -> None:
    """Simulated robots publish as rmw_zenoh nodes; the server's poses, attachments and
    liveliness tokens are read by a subscriber that knows only the design document's formats."""
    srv_session, client = sessions
    sim, config = simulated_team(seed=0, duration=8.0)
    rate = 4.0
    poses: list[tuple[str, bytes, bytes | None]] = []
    lock = threading.Lock()

    def on_pose(sample: Any) -> None:
        att = sample.attachment
        with lock:
            poses.append(
                (str(sample.key_expr), sample.payload.to_bytes(), att.to_bytes() if att else None)
            )

    # "<domain_id>/<fully qualified name>/<type name>/<type hash>", any robot, any hash
    sub = client.declare_subscriber("0/relloc/*/pose/*/*", on_pose)
    announced: list[str] = []  # every liveliness token that appeared (the robots' come and go)
    lv_sub = client.liveliness().declare_subscriber(
        "@ros2_lv/0/**", lambda s: announced.append(str(s.key_expr)), history=True
    )
    collector = EstimateCollector(client, config, interface=RMW)
    server = LiveServer(
        config,
        srv_session,
        ServeOptions(particles=1000, clock_rate=rate, interface=RMW, trace=True),
    )
    server.start()
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        stats = publish_events(
            sim.events(), config, client, rate=rate, interface=RMW, time_base=T0, wait=5.0
        )
        assert stats.unmatched == []
        assert wait_until(lambda: server.source.stats.events.total() >= stats.messages)
        tokens = [str(r.ok.key_expr) for r in client.liveliness().get("@ros2_lv/0/**", timeout=2.0)]
    finally:
        server.stop()
        thread.join(timeout=10)
    n_own = len(server.pipelines[0].estimates)  # the last one was published as the server ended
    assert wait_until(
        lambda: (
            len(collector.estimates()) >= n_own
            and len(poses) >= 4 * n_own
            and set(collector.estimates()[-1].positions) == set(config.others)
        )
    )
    estimates = collector.estimates()
    traces = collector.traces()
    server.close()
    collector.close()
    sub.undeclare()
    lv_sub.undeclare()

    own = server.pipelines[0].estimates
    assert len(own) > 40 and len(estimates) == len(own)
    with lock:
        received = list(poses)
    assert len(received) == len(own) * len(config.others)
    hash_ = "RIHS01_" + PUBLISHED_HASHES[POSE_WITH_COVARIANCE_STAMPED]
    sequences: dict[bytes, list[int]] = {}
    for key, payload, att in received:
        domain, ns, robot, leaf, typename, type_hash_ = key.split("/")
        assert (domain, ns, leaf) == ("0", "relloc", "pose") and robot in config.others
        assert typename == "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
        assert type_hash_ == hash_
        msg = decode(payload, POSE_WITH_COVARIANCE_STAMPED)
        # the heading frame, or the formation in its gauge while the orientation is a gauge
        assert msg.header.frame_id in (config.reference, f"{config.reference}/formation")
        assert att is not None and len(att) == 33 and att[16] == 16
        seq, stamp = struct.unpack_from("<qq", att)
        assert abs(stamp * 1e-9 - time.time()) < 60
        sequences.setdefault(att[17:], []).append(seq)
    assert len(sequences) == len(config.others)  # one publisher (GID) per robot's topic
    assert all(s == list(range(1, len(s) + 1)) for s in sequences.values())
    last = estimates[-1]
    assert last.positions["r1"] == pytest.approx(own[-1].positions["r1"])

    # Liveliness: relloc's node and its publishers, in the design document's format.
    nodes = [t.split("/") for t in tokens if t.split("/")[5] == "NN"]
    assert [n[8] for n in nodes if n[8] == "relloc"] == ["relloc"]
    pubs = [t.split("/") for t in tokens if t.split("/")[5] == "MP" and t.split("/")[8] == "relloc"]
    topics = {p[9] for p in pubs}
    assert {f"%relloc%{r}%pose" for r in config.others} | {"%relloc%status"} <= topics
    subs = {
        t.split("/")[9] for t in tokens if t.split("/")[5] == "MS" and t.split("/")[8] == "relloc"
    }
    assert {"%r1%odom", "%uwb%tof%n_1%n_2%distance", "%uwb%tof%n_2%n_1%distance"} <= subs
    for p in pubs:
        assert p[:2] == ["@ros2_lv", "0"] and p[6:8] == ["%", "%"] and len(p) == 13
        if p[9].endswith("%pose"):
            assert p[10:12] == ["geometry_msgs::msg::dds_::PoseWithCovarianceStamped_", hash_]
    sim_pubs = [
        t
        for t in set(announced)
        if "/MP/%/%/relloc_events/%r1%odom/nav_msgs::msg::dds_::Odometry_/" in t
    ]
    assert len(sim_pubs) == 1 and sim_pubs[0].endswith(
        "RIHS01_" + PUBLISHED_HASHES[ODOMETRY] + "/::,10:,:,:,,"
    )
    # The robots' attachments: no loss, no foreign hash; their timestamps give the latency.
    tr = server.summary()["source"]["transport"]
    assert tr["lost"] == {} and tr["attachment_missing"] == tr["attachment_malformed"] == 0
    assert tr["unknown_type_hash"] == {} and tr["publishers"] == len(stats.per_key) == 15
    assert server.summary()["source"]["rejected"] == {}
    latency = [r["published"] - r["trigger_sent"] for r in traces if r["trigger_sent"]]
    assert len(latency) >= len(own) - 2 and min(latency) > 0.0 and max(latency) < 1.0


def test_malformed_attachments_and_foreign_types_over_zenoh(sessions: tuple[Any, Any]) -> None:
    srv_session, client = sessions
    _, config = simulated_team(seed=0, duration=5.0)
    source = ZenohSource(config, ZenohSourceOptions(interface=RMW))
    source.attach(srv_session)
    channel = RMW.channel("/r1/odom", ODOMETRY)
    keys = [
        channel.key,
        f"0/r1/odom/{dds_type_name(ODOMETRY)}/RIHS01_{'f' * 64}",
        "0/r1/odom/std_msgs::msg::dds_::String_/RIHS01_df668c74",
    ]
    pubs = [client.declare_publisher(k) for k in keys]
    try:
        assert wait_until(lambda: all(p.matching_status.matching for p in pubs))
        good = _odom(T0)
        pubs[0].put(good, attachment=b"\x01\x02\x03")
        pubs[0].put(_odom(T0 + 0.05))  # no attachment
        pubs[1].put(_odom(T0 + 0.1), attachment=RmwAttachment(1, 0, b"\x05" * 16).encode())
        pubs[2].put(b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00")
        released: list[Any] = []
        # The foreign type was put last: wait for its rejection too, not only for the three
        # events (then a little longer, for anything that should not come).
        assert wait_until(
            lambda: (
                bool(released.extend(source.poll(0.05)))
                or (len(released) >= 3 and sum(source.stats.rejected.values()) >= 1)
            )
        )
        time.sleep(0.1)
        released.extend(source.drain())
    finally:
        for p in pubs:
            p.undeclare()
        source.detach()
    assert len(released) == 3
    assert source.stats.rejected == {"unknown_type": 1}
    tr = source.transport
    assert (tr.attachment_malformed, tr.attachment_missing, tr.unknown_type_hash.total()) == (
        1,
        1,
        1,
    )


def test_replay_on_rmw_zenoh_leaves_out_topics_whose_type_it_cannot_hash() -> None:
    """A bag topic of a type relloc has no definition of has no rmw_zenoh key: skipped, logged."""
    from relloc.live.publish import _topic_channels

    _, config = simulated_team(seed=0, duration=5.0)
    topics = {"/r1/odom": ODOMETRY, "/x/y": "foo_msgs/msg/Unknown"}
    channels = _topic_channels(config, RMW, "", topics)
    assert list(channels) == ["/r1/odom"]
    assert channels["/r1/odom"] == RMW.channel("/r1/odom", ODOMETRY)
    assert list(_topic_channels(config, RosInterface(), "", topics)) == ["/r1/odom", "/x/y"]
