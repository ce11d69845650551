"""The live ROS 2 bridge over loopback tcp only: a Zenoh router (the role of ``rmw_zenohd``), the bridge node
over the mock bus, and a ROS 2 client we did not write (zenoh-ros2-sdk, in its own process:
ros2_sdk_client.py) that decodes a camera frame and a depth point cloud bit for bit, the camera info and
info record, sees the node, its topics and its services through the liveliness tokens, and calls the
start-scan and plan services. Also: the raw samples on the key and with the attachment rmw_zenoh's design
document gives, a router of another Zenoh release refused in one line, an absent router in one line, and the
TLS tether: mutual TLS where the rig's CA is the allow-list on both ends (certificates made with the openssl
command line)."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh  # the test extra: a missing package fails here, it is not skipped
from polarstripe.msgs import DepthMap, Frame, Header, Log, Plan, ScanEvent, ScanRequest
from polarstripe.nodes.ros2_bridge import Ros2Bridge
from polarstripe.nodes.ros2_zenoh import parse_attachment
from polarstripe.runtime.mock_bus import MockBus
from polarstripe.runtime.node import NodeError

CLIENT = Path(__file__).with_name("ros2_sdk_client.py")
IMAGE_KEY = ("0/rig/camera/frame/image/sensor_msgs::msg::dds_::Image_/"
             "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47")
# the third-party client as a peer of the router, as rmw_zenoh's sessions are (its ZENOH_SESSION_CONFIG_URI),
# listening on loopback only and without scouting (its bundled default configuration is for a newer Zenoh)
CLIENT_CONFIG = {"mode": "peer", "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
                 "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}


def bridge(port: int, **params) -> Ros2Bridge:
    bus = MockBus()
    bus.graph = {
        "launch": "t",
        "nodes": {"simulator": {"module": "polarstripe.nodes.simulator", "params": {}}},
        "topics": {"/rig/camera/frame": {"type": "frame"}, "/rig/log": {"type": "log"},
                   "/rig/compositor/depth": {"type": "depth_map"}},
        "services": {"/rig/emitter/start_scan": {"node": "emitter"},
                     "/rig/planner/plan": {"node": "planner"}},
    }
    params = {"endpoint": f"tcp/127.0.0.1:{port}", "connect_timeout_s": 3.0, **params}
    return Ros2Bridge("ros2", namespace="/rig", params=params, bus=bus)


def _client_session(port: int):
    c = zenoh.Config()
    for k, v in {"mode": "client", "connect/endpoints": [f"tcp/127.0.0.1:{port}"],
                 "scouting/multicast/enabled": False, "scouting/gossip/enabled": False}.items():
        c.insert_json5(k, json.dumps(v))
    return zenoh.open(c)


def start_scan(req: ScanRequest) -> ScanEvent:
    if not req.method:
        raise ValueError("a scan needs a method")
    return ScanEvent(scan_id=7, event="start", method=req.method, analyzer_deg=req.analyzer_deg)


def test_third_party_client_decodes_frames_sees_the_graph_and_calls_a_service(zenoh_router, ros2_msgs_dir,
                                                                              tmp_path):
    config = tmp_path / "session.json5"
    config.write_text(json.dumps(CLIENT_CONFIG))
    node = bridge(zenoh_router)
    node.setup()
    node._bus.responders["/rig/emitter/start_scan"] = start_scan
    node._bus.responders["/rig/planner/plan"] = lambda req: Plan(
        modality="stripes", separation_m=0.166, scan_type="translate", stripe_optima=[0.1, 0.2],
        curves={"quality": np.array([0.5, 0.75, 0.25])})
    img = (np.arange(24 * 32, dtype=np.uint16).reshape(24, 32) * 67) ^ 0x5A5A
    frame = Frame(image=img, exposure_s=0.01, pattern="stripe:1/4", polarizer_deg=90.0,
                  header=Header(stamp_ns=1_700_000_000_123_456_789, seq=4, frame_id="camera"))
    points = np.array([[0.01, -0.02, 0.31], [-0.1, 0.05, 0.29], [0.0, 0.0, 0.5]], np.float32)
    depth = DepthMap(depth_m=np.full((24, 32), np.nan, np.float32), points_m=points, method="stripes")
    raw = _client_session(zenoh_router)
    samples = []
    raw.declare_subscriber(IMAGE_KEY, lambda s: samples.append(s.attachment.to_bytes()))
    proc = subprocess.Popen([sys.executable, str(CLIENT), str(zenoh_router), str(ros2_msgs_dir)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "ZENOH_SESSION_CONFIG_URI": str(config)})
    lines: list[dict] = []

    def read():
        for line in proc.stdout:
            lines.append(json.loads(line))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 60
        while not any("done" in x or "error" in x for x in lines) and time.monotonic() < deadline:
            if proc.poll() is not None:
                break
            node.forward("/rig/camera/frame", frame)
            node.forward("/rig/log", Log(level="ERROR", node="grabber", text="lost",
                                         header=Header(stamp_ns=5)))
            node.forward("/rig/compositor/depth", depth)
            node.answer_requests()
            time.sleep(0.05)
        proc.wait(10)
        reader.join(5)
        out = {k: v for x in lines for k, v in x.items() if k != "topic"}
        topics = {x["topic"]: x for x in lines if "topic" in x}
        assert "done" in out, f"client: {lines} {proc.stderr.read()[-2000:]}"
    finally:
        if proc.poll() is None:
            proc.kill()
        raw.close()
        node.teardown()

    image = topics["/rig/camera/frame/image"]
    assert (image["height"], image["width"], image["encoding"], image["step"], image["bigendian"]) == (
        24, 32, "mono16", 64, 0)
    assert image["sha256"] == hashlib.sha256(img.astype("<u2").tobytes()).hexdigest()
    assert (image["stamp_ns"], image["frame_id"]) == (1_700_000_000_123_456_789, "camera")
    info = topics["/rig/camera/frame/camera_info"]
    assert (info["width"], info["height"]) == (32, 24) and info["k"][8] == 1.0 and info["k"][0] > 0
    cloud = topics["/rig/compositor/depth/points"]
    assert (cloud["width"], cloud["point_step"], cloud["fields"]) == (3, 12, ["x", "y", "z"])
    assert cloud["sha256"] == hashlib.sha256(points.astype("<f4").tobytes()).hexdigest()
    assert topics["/rig/camera/frame/info"]["pattern"] == "stripe:1/4"
    frame_info = topics["/rig/camera/frame/info"]
    assert (frame_info["polarizer_deg"], frame_info["seq"]) == (90.0, 4)

    assert any(n.endswith("/NN/%/%rig/polarstripe") for n in out["nodes"]), out["nodes"]
    names = dict((t, tuple(types)) for t, types in out["topics"])
    assert names["/rig/camera/frame/image"] == ("sensor_msgs/msg/Image",)
    assert names["/rig/camera/frame/info"] == ("polarstripe_msgs/msg/FrameInfo",)
    assert names["/tf_static"] == ("tf2_msgs/msg/TFMessage",)
    assert names["/rosout"] == ("rcl_interfaces/msg/Log",)
    image_hash = IMAGE_KEY.rsplit("/", 1)[1]
    assert out["image_publishers"] == [["/rig", "polarstripe", "sensor_msgs/msg/Image", image_hash]]
    assert ["/rig/emitter/start_scan", ["polarstripe_msgs/srv/StartScan"]] in out["services"]

    assert out["start_scan"] == {"ok": True, "detail": "", "scan_id": 7, "event": "start", "method": "flood",
                                 "analyzer_deg": [10.0, 100.0]}
    sent = node._bus.clients["/rig/emitter/start_scan"].requests
    assert (sent[0].method, sent[0].stripes, sent[0].analyzer_deg) == ("flood", 0, [10.0, 100.0])
    assert out["refused"]["ok"] is False and "a scan needs a method" in out["refused"]["detail"]
    assert out["plan"] == {"ok": True, "modality": "stripes", "separation_m": 0.166,
                           "curves": {"quality": [0.5, 0.75, 0.25]}}

    # the raw samples: on the design document's key, each with the 33-byte attachment, numbered from 1
    seqs = [parse_attachment(a) for a in samples]
    assert len(seqs) >= 2 and [s for s, _, _ in seqs] == list(range(seqs[0][0], seqs[0][0] + len(seqs)))
    assert len({g for _, _, g in seqs}) == 1 and abs(seqs[-1][1] - time.time_ns()) < 120e9


def test_a_router_of_another_zenoh_release_is_refused_in_one_line(zenoh_router):
    """The router's own record names no release (a wheel built from a commit); a second record, as a router
    of Zenoh 1.6.2 (ROS 2 Jazzy's rmw_zenoh 0.2.9) writes it, is answered from the admin space's key."""
    other = _client_session(zenoh_router)
    key = "@/0123456789abcdef0123456789abcdef/router"
    fake = other.declare_queryable(key, lambda q: q.reply(
        key, json.dumps({"zid": "0123456789abcdef", "version": "v1.6.2 built with rustc 1.75.0"})))
    time.sleep(0.3)  # the router has the declaration
    try:
        node = bridge(zenoh_router)
        with pytest.raises(NodeError) as err:
            node.setup()
        text = str(err.value)
        assert "\n" not in text and "Zenoh 1.6.2" in text and "1.4" in text
    finally:
        fake.undeclare()
        other.close()


def test_no_router_is_one_line(zenoh_router):
    node = bridge(zenoh_router + 0, endpoint="tcp/127.0.0.1:9", connect_timeout_s=0.5)
    with pytest.raises(NodeError, match=r"^node 'ros2': ROS 2 router tcp/127.0.0.1:9: .*connect") as err:
        node.setup()
    assert "\n" not in str(err.value)
    for bad, match in (({"domain": 300}, "ros2_domain"), ({"ros_node": "rig view"}, "node name"),
                       ({"endpoint": "udp/127.0.0.1:7447"}, "tcp/HOST:PORT")):
        with pytest.raises(NodeError, match=match):
            bridge(zenoh_router, **bad).setup()


def _certificates(folder: Path) -> None:
    """Two CAs (the rig's, a stranger's); the router and the vehicle signed by the rig's, a stranger by the
    other (EC P-256, valid for localhost and 127.0.0.1)."""
    def run(*args):
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)

    for ca in ("rigca", "otherca"):
        run("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-keyout",
            f"{ca}.key", "-out", f"{ca}.pem", "-days", "2", "-subj", f"/CN={ca}")
    (folder / "san.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    for name, ca in (("router", "rigca"), ("vehicle", "rigca"), ("stranger", "otherca"), ("fake", "otherca")):
        run("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-keyout",
            f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}")
        run("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
            "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", "san.ext")


def _tls_router(folder: Path, port: int, name: str, ca: str):
    c = zenoh.Config()
    for k, v in {"mode": "router", "listen/endpoints": [f"tls/127.0.0.1:{port}"], "connect/endpoints": [],
                 "scouting/multicast/enabled": False, "scouting/gossip/enabled": False,
                 "transport/link/tls/root_ca_certificate": str(folder / f"{ca}.pem"),
                 "transport/link/tls/listen_certificate": str(folder / f"{name}.pem"),
                 "transport/link/tls/listen_private_key": str(folder / f"{name}.key"),
                 "transport/link/tls/enable_mtls": True}.items():
        c.insert_json5(k, json.dumps(v))
    return zenoh.open(c)


def test_tls_tether_admits_the_rigs_certificates_only(tmp_path):
    _certificates(tmp_path)
    port = _free_port()
    router = _tls_router(tmp_path, port, "router", "rigca")
    try:
        def tls_bridge(name):
            return bridge(0, endpoint=f"tls/localhost:{port}", connect_timeout_s=0.5,
                          tls_ca=str(tmp_path / "rigca.pem"), tls_cert=str(tmp_path / f"{name}.pem"),
                          tls_key=str(tmp_path / f"{name}.key"))

        (tmp_path / "vehicle.key").chmod(0o644)
        with pytest.raises(NodeError, match=r"tls_key: .*vehicle\.key is readable by others .*chmod 600"):
            tls_bridge("vehicle").setup()
        (tmp_path / "vehicle.key").chmod(0o600)
        with pytest.raises(NodeError, match="tls_cert .*nobody.pem does not exist"):
            tls_bridge("nobody").setup()
        node = tls_bridge("vehicle")
        node.setup()  # the rig's certificate: admitted, and the router's is the rig CA's
        node.teardown()
        with pytest.raises(NodeError, match=f"ROS 2 router tls/localhost:{port}: .*connect"):
            tls_bridge("stranger").setup()  # another CA's certificate: the router hangs up
    finally:
        router.close()
    impostor = _tls_router(tmp_path, port, "fake", "otherca")  # a router the rig's CA did not sign
    try:
        with pytest.raises(NodeError, match="connect"):
            tls_bridge("vehicle").setup()
    finally:
        impostor.close()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_bench_ros2_runs_on_a_small_frame():
    from polarstripe.bench.ros2 import run

    result = run([(32, 24)], 3)
    rows = {r["row"]: r for r in result["rows"]}
    assert set(rows) == {"bridge", "zenoh put", "memcpy"}
    assert all(r["received"] == r["sent"] == 3 and r["cpu_ms_per_frame"] >= 0 for r in rows.values())
    assert rows["zenoh put"]["cpu_vs_put"] == 1.0 and rows["bridge"]["latency_ms"] > 0
