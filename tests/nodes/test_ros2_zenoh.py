"""rmw_zenoh's wire formats (nodes/ros2_zenoh.py) against the examples of its design document (docs/design.md
in ros2/rmw_zenoh, copied here verbatim) and against the third-party client's (zenoh-ros2-sdk) own
encoders."""

from __future__ import annotations

import json

import pytest
from polarstripe.nodes.ros2_zenoh import (
    ATTACHMENT_BYTES,
    PUBLISHER,
    SERVICE,
    SUBSCRIPTION,
    TRANSIENT_LOCAL,
    Entity,
    Ros2FormatError,
    attachment,
    data_key,
    parse_attachment,
    qos_key,
    session_config,
    version_mismatch,
)

STRING = ("std_msgs/msg/String", "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
ADD = ("example_interfaces/srv/AddTwoInts",
       "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a")


def test_data_keys_as_in_the_design_document():
    assert data_key(0, "/chatter", *STRING) == (
        "0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
    assert data_key(0, "/robot1/chatter", *STRING) == (
        "0/robot1/chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
    assert data_key(2, "/add_two_ints", *ADD) == (
        "2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/"
        "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a")


def test_liveliness_tokens_as_in_the_design_document():
    listener = Entity(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener")
    assert listener.node_token() == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert listener.token(SUBSCRIPTION, 10, "/chatter", *STRING, qos_key()) == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,")
    talker = Entity(2, "8b20917502ee955ac4476e0266340d5c", 0, "/", "talker")
    assert talker.token(PUBLISHER, 10, "/chatter", *STRING, qos_key(depth=7)) == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,")
    server = Entity(2, "f9980ee0495eaafb3e38f0d19e2eae12", 0, "/", "add_two_ints_server")
    assert server.token(SERVICE, 10, "/add_two_ints", *ADD, qos_key()) == (
        "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/%add_two_ints/"
        "example_interfaces::srv::dds_::AddTwoInts_/"
        "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a/::,10:,:,:,,")
    rig = Entity(0, "ab", 0, "/rig", "polarstripe")
    assert rig.node_token() == "@ros2_lv/0/ab/0/0/NN/%/%rig/polarstripe"
    assert "/polarstripe/%rig%camera%frame%image/" in rig.token(PUBLISHER, 1, "/rig/camera/frame/image",
                                                               *STRING, qos_key())


def test_qos_agrees_with_the_third_party_client():
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile

    latched = qos_key(durability=TRANSIENT_LOCAL, depth=1)
    assert latched == ":1:,1:,:,:,,"
    assert QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1).encode() == latched
    back = QosProfile.decode(latched)
    assert back.durability == QosDurability.TRANSIENT_LOCAL and back.history_depth == 1
    assert QosProfile().encode() == qos_key()


def test_attachment_is_33_bytes_and_agrees_with_the_third_party_client():
    from zenoh_ros2_sdk.attachment import Attachment

    gid = bytes(range(16))
    a = attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(a) == ATTACHMENT_BYTES == 33 and a[16] == 16
    theirs = Attachment.from_bytes(a)
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (7, 1_700_000_000_123_456_789, gid)
    assert parse_attachment(Attachment(sequence_id=3, timestamp_ns=5, gid=gid).to_bytes()) == (3, 5, gid)
    for bad in (None, a[:32], a[:16] + b"\x08" + a[17:]):
        with pytest.raises(Ros2FormatError, match="33 bytes"):
            parse_attachment(bad)
    with pytest.raises(Ros2FormatError, match="16 bytes"):
        attachment(1, 1, b"short")


def test_gids_differ_per_entity_and_session():
    e = Entity(0, "aa", 0, "/rig", "n")
    gids = {e.gid(1), e.gid(2), Entity(0, "bb", 0, "/rig", "n").gid(1)}
    assert len(gids) == 3 and all(len(g) == 16 for g in gids)


def test_bad_names_domains_and_types_are_refused():
    with pytest.raises(Ros2FormatError, match="ros2_domain"):
        data_key(233, "/a", *STRING)
    with pytest.raises(Ros2FormatError, match="ros2_domain"):
        Entity(-1, "aa", 0, "/", "n").node_token()
    for name in ("chatter", "/a/", "/a//b", "/a b"):
        with pytest.raises(Ros2FormatError, match="fully qualified"):
            data_key(0, name, *STRING)
    with pytest.raises(Ros2FormatError, match="pkg/msg/Name"):
        data_key(0, "/a", "String", "RIHS01_x")
    with pytest.raises(Ros2FormatError, match="node name"):
        Entity(0, "aa", 0, "/", "my-node").node_token()
    with pytest.raises(Ros2FormatError, match="MP, MS, SS or SC"):
        Entity(0, "aa", 0, "/", "n").token("NN", 1, "/a", *STRING, qos_key())


def test_session_config_is_a_client_of_one_router_without_scouting():
    c = {k: json.loads(v) for k, v in session_config("tcp/127.0.0.1:7447").items()}
    assert c["mode"] == "client" and c["connect/endpoints"] == ["tcp/127.0.0.1:7447"]
    assert c["listen/endpoints"] == []
    assert not c["scouting/multicast/enabled"] and not c["scouting/gossip/enabled"]
    tls = {k: json.loads(v) for k, v in session_config("tls/rov:7447", tls_ca="ca.pem", tls_cert="c.pem",
                                                        tls_key="k.pem").items()}
    assert tls["transport/link/tls/enable_mtls"] and tls["transport/link/tls/root_ca_certificate"] == "ca.pem"
    for endpoint, kw, match in (("udp/1.2.3.4:7447", {}, "tcp/HOST:PORT"), ("tcp/host", {}, "tcp/HOST:PORT"),
                                ("tls/h:1", {"tls_ca": "a"}, "needs tls_ca"),
                                ("tcp/h:1", {"tls_ca": "a"}, "for a tls/ endpoint")):
        with pytest.raises(Ros2FormatError, match=match):
            session_config(endpoint, **kw)


def test_version_mismatch_names_both_versions():
    record = json.dumps({"zid": "abc", "version": "v1.6.2 built with rustc 1.75.0"}).encode()
    line = version_mismatch("1.4.0", record)
    assert line is not None and "1.6.2" in line and "1.4.0" in line and "\n" not in line
    assert version_mismatch("1.4.0", json.dumps({"version": "v1.4.1 built"}).encode()) is None
    assert version_mismatch("1.4.0", json.dumps({"version": "vb70ee933 built with rustc"}).encode()) is None
    assert version_mismatch("1.4.0", b"not json") is None
