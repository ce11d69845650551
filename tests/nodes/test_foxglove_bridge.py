"""The live Foxglove bridge, spoken to as the Foxglove app does (WebSocket, subprotocol ``foxglove.sdk.v1`` /
``foxglove.websocket.v1``, loopback only): in process over the mock bus, and in ``launch/sim.toml`` with
``foxglove=true``, where a client subscribes to the composite channel and decodes an image. The recording of
that launch then goes through both exports, the import and ``launch/replay.toml``."""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from polarstripe.msgs import Composite, Frame, Header, Log, PolarizerState
from polarstripe.runtime.mock_bus import MockBus

pytest.importorskip("foxglove", reason="CI installs the test extra (foxglove-sdk)")
pytest.importorskip("google.protobuf", reason="CI installs the test extra (protobuf)")

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402
from polarstripe.nodes.foxglove_bridge import FoxgloveBridge  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")


class WsClient:
    """The smallest WebSocket client of the Foxglove protocol: handshake, JSON text, binary messages."""

    def __init__(self, port: int, timeout_s: float = 10.0):
        self.s = socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
        self.adv: dict[str, dict] = {}  # topic -> channel, from every advertise seen
        key = base64.b64encode(os.urandom(16)).decode()
        self.s.sendall(
            (f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
             f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
             f"Sec-WebSocket-Protocol: {', '.join(SUBPROTOCOLS)}\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.s.recv(1)
        assert head.startswith(b"HTTP/1.1 101"), head
        proto = re.search(rb"(?i)sec-websocket-protocol:\s*([^\r]+)", head)
        assert proto and proto[1].decode().strip() in SUBPROTOCOLS, head

    def _exact(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.s.recv(n - len(out))
            assert chunk, "connection closed"
            out += chunk
        return out

    def recv(self):
        b0, b1 = self._exact(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._exact(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._exact(8))[0]
        data = self._exact(n)
        if b0 & 0x0F not in (1, 2):  # ping, pong, continuation: not used by this server here
            return self.recv()
        msg = json.loads(data) if b0 & 0x0F == 1 else data
        if isinstance(msg, dict) and msg.get("op") == "advertise":
            self.adv.update({c["topic"]: c for c in msg["channels"]})
        return msg

    def send_json(self, obj) -> None:
        data, mask = json.dumps(obj).encode(), os.urandom(4)
        n = len(data)
        size = bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
        self.s.sendall(bytes([0x81]) + size + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def until(self, pred, timeout_s=10.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            msg = self.recv()
            if pred(msg):
                return msg
        raise AssertionError("not received")

    def subscribe(self, topic: str, sub_id: int) -> dict:
        ch = self.adv[topic]
        self.send_json({"op": "subscribe", "subscriptions": [{"id": sub_id, "channelId": ch["id"]}]})
        return ch

    def close(self) -> None:
        self.s.close()


def decoder(channel: dict):
    """Decode a channel's messages as the app does: protobuf from the advertised descriptor set, or JSON."""
    if channel["encoding"] == "json":
        return json.loads
    assert (channel["encoding"], channel["schemaEncoding"]) == ("protobuf", "protobuf")
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"])).FromString


def message_data(msg, sub_id: int):
    """(log time, payload) of a binary message-data frame for subscription ``sub_id``, else None."""
    if isinstance(msg, bytes) and msg[0] == 1 and struct.unpack("<I", msg[1:5])[0] == sub_id:
        return struct.unpack("<Q", msg[5:13])[0], msg[13:]
    return None


def _poll(ws, send, sub_id, tries=40):
    """Call ``send`` until the server delivers a message of subscription ``sub_id`` (it applies a subscription
    asynchronously)."""
    ws.s.settimeout(0.3)
    try:
        for _ in range(tries):
            send()
            try:
                return message_data(ws.until(lambda m: message_data(m, sub_id) is not None, 0.3), sub_id)
            except (TimeoutError, AssertionError):
                continue
    finally:
        ws.s.settimeout(10)
    raise AssertionError(f"no message on subscription {sub_id}")


def test_bridge_serves_foxglove_schemas_on_loopback():
    bus = MockBus()
    bus.graph = {
        "launch": "t",
        "nodes": {"simulator": {"module": "polarstripe.nodes.simulator", "params": {}}},
        "topics": {"/rig/camera/frame": {"type": "frame"}, "/rig/compositor/composite": {"type": "composite"},
                   "/rig/log": {"type": "log"}, "/rig/polarizer/state": {"type": "polarizer_state"}},
    }
    node = FoxgloveBridge("foxglove", namespace="/rig", params={"port": 0}, bus=bus)
    node.setup()
    try:
        assert node.port > 0 and node.params.host == "127.0.0.1"
        ws = WsClient(node.port)
        ws.until(lambda m: "/tf_static" in ws.adv)
        tf_ch = ws.subscribe("/tf_static", 1)
        _, data = _poll(ws, node._resend_static, 1)
        tf = decoder(tf_ch)(data)
        assert {(t.parent_frame_id, t.child_frame_id) for t in tf.transforms} == {
            ("tank", "camera"), ("camera", "polarizer"), ("tank", "projector")}
        img = np.arange(24 * 32, dtype=np.uint16).reshape(24, 32) * 5
        frame = Frame(image=img, exposure_s=0.01, pattern="stripe:1/4", polarizer_deg=90.0,
                      header=Header(stamp_ns=123456789, seq=4))
        node.forward("/rig/camera/frame", frame)
        ws.until(lambda m: "/rig/camera/frame/image" in ws.adv and "/rig/camera/frame/info" in ws.adv)
        ch = ws.subscribe("/rig/camera/frame/image", 7)
        assert ch["schemaName"] == "foxglove.RawImage"
        log_time, data = _poll(ws, lambda: node.forward("/rig/camera/frame", frame), 7)
        raw = decoder(ch)(data)
        assert log_time == 123456789
        assert (raw.width, raw.height, raw.encoding, raw.step) == (32, 24, "mono16", 64)
        assert np.array_equal(np.frombuffer(raw.data, "<u2").reshape(24, 32), img)
        info_ch = ws.subscribe("/rig/camera/frame/info", 8)
        assert info_ch["schemaName"] == "polarstripe.FrameInfo" and info_ch["schemaEncoding"] == "jsonschema"
        _, data = _poll(ws, lambda: node.forward("/rig/camera/frame", frame), 8)
        assert decoder(info_ch)(data)["pattern"] == "stripe:1/4"
        node.forward("/rig/log", Log(level="ERROR", node="grabber", text="lost", header=Header(stamp_ns=5)))
        node.forward("/rig/polarizer/state", PolarizerState(angle_deg=12.5, target_deg=12.5, settled=True))
        comp = Composite(images={"composite": np.ones((24, 32), np.float32)}, method="flood")
        node.forward("/rig/compositor/composite", comp)
        wanted = {"/rig/log", "/rig/polarizer/state", "/rig/compositor/composite/metrics"}
        ws.until(lambda m: wanted <= set(ws.adv))
        assert ws.adv["/rig/log"]["schemaName"] == "foxglove.Log"
        st = ws.subscribe("/rig/polarizer/state", 9)
        _, data = _poll(ws, lambda: node.forward("/rig/polarizer/state", PolarizerState(
            angle_deg=12.5, target_deg=12.5, settled=True)), 9)
        assert decoder(st)(data)["angle_deg"] == 12.5
        ws.close()
    finally:
        node.teardown()


def test_depth_points_are_a_foxglove_point_cloud():
    from polarstripe.msgs import DepthMap
    from polarstripe.nodes.foxglove_schemas import FoxgloveEncoder
    from polarstripe.nodes.rig_views import Points, RigViews

    points = np.array([[0.01, -0.02, 0.31], [-0.1, 0.05, 0.29], [0.0, 0.0, 0.5]], np.float32)
    msg = DepthMap(depth_m=np.ones((2, 2), np.float32), points_m=points, method="stripes")
    view = next(v for v in RigViews(None).views("/rig/compositor/depth", 1, msg) if isinstance(v, Points))
    e = FoxgloveEncoder().encode(view)
    channel = {"encoding": e.schema.message_encoding, "schemaEncoding": e.schema.encoding,
               "schema": base64.b64encode(e.schema.data).decode(), "schemaName": e.schema.name}
    cloud = decoder(channel)(b"".join(e.parts))
    assert (e.topic, e.schema.name) == ("/rig/compositor/depth/points", "foxglove.PointCloud")
    assert cloud.point_stride == 12  # FLOAT32 = 7:
    assert [(f.name, f.offset, f.type) for f in cloud.fields] == [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
    assert np.array_equal(np.frombuffer(cloud.data, "<f4").reshape(-1, 3), points)


# ---- in launch/sim.toml ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    """``launch sim.toml --once --record run.mcap foxglove=true foxglove_port=0`` at a small size; meanwhile a
    WebSocket client subscribes to the composite channel and decodes one image. The small demo can end before
    an external client has subscribed on a loaded machine (the channel is advertised with its first message,
    and the launch ends with the sequencer): then it is run once more, and a second miss fails."""
    run = _sim_run_once(tmp_path_factory)
    if "connection closed" in run.get("error", ""):
        run = _sim_run_once(tmp_path_factory)
    return run


def _sim_run_once(tmp_path_factory) -> dict:
    tmp = tmp_path_factory.mktemp("sim_fox")
    can = tempfile.mkdtemp(prefix="ps-can-", dir="/tmp")  # ipc paths are limited to ~107 bytes
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp / "runs")}
    cmd = [sys.executable, "-m", "polarstripe", "launch", str(ROOT / "launch" / "sim.toml"), "--once",
           "--record", str(tmp / "run.mcap"), f"out={tmp / 'out'}", "resolution=96x72", "stripes=8",
           f"can=ipc://{can}/bus", "foxglove=true", "foxglove_port=0"]
    proc = subprocess.Popen(cmd, cwd=tmp, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    got: dict = {}
    try:
        deadline = time.monotonic() + 90
        port = None
        while port is None and time.monotonic() < deadline and proc.poll() is None:
            for log in (tmp / "runs").glob("*/logs/foxglove.log"):
                if m := re.search(r"Foxglove WebSocket on ws://127\.0\.0\.1:(\d+)", log.read_text()):
                    port = int(m[1])
            time.sleep(0.1)
        assert port, "the bridge did not start"
        ws = WsClient(port, timeout_s=60)
        topic = "/rig/compositor/composite/composite"
        ws.until(lambda m: topic in ws.adv, timeout_s=90)
        ch = ws.subscribe(topic, 3)
        log_time, data = message_data(ws.until(lambda m: message_data(m, 3) is not None, timeout_s=60), 3)
        got.update(channel=ch, log_time=log_time, image=decoder(ch)(data), advertised=set(ws.adv))
        ws.close()
    except (AssertionError, OSError) as exc:  # reported with the launch's own account of what happened
        got["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        try:
            _, err = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        shutil.rmtree(can, ignore_errors=True)
    logs = {p.stem: p.read_text() for p in (tmp / "runs").glob("*/logs/*.log")}
    got.update(tmp=tmp, returncode=proc.returncode, stderr=err, bag=tmp / "run.mcap", logs=logs)
    return got


def _launch_ok(run) -> None:
    """The client got its image and the launch recorded; else what the launch and its nodes said. The
    launch's exit status is not checked: a scan that faults (the simulated drive missing a heartbeat on a
    loaded machine ends the sequencer with 1) does not concern the bridge or the exports."""
    why = run.get("error") or (not run["bag"].is_file() and f"no recording (launch exit {run['returncode']})")
    if why:
        tails = "\n".join(f"--- {name}:\n{text[-1500:]}" for name, text in sorted(run["logs"].items())
                          if "Traceback" in text or "ERROR" in text)
        pytest.fail(f"{why}\n--- launch stderr:\n{run['stderr'][-2000:]}\n{tails}")


@pytest.mark.slow
def test_sim_launch_with_foxglove_serves_a_composite_image(sim_run):
    _launch_ok(sim_run)
    img = sim_run["image"]
    assert sim_run["channel"]["schemaName"] == "foxglove.RawImage"
    assert (img.width, img.height, img.encoding, img.step) == (96, 72, "32FC1", 96 * 4)
    pixels = np.frombuffer(img.data, "<f4").reshape(72, 96)
    assert np.isfinite(pixels).all() and pixels.max() > 0
    assert {"/tf_static", "/rig/camera/frame/image", "/rig/polarizer/state"} <= sim_run["advertised"]


@pytest.mark.slow
def test_sim_recording_exports_imports_and_replays(sim_run):
    from polarstripe.runtime.bag_reader import BagReader
    from polarstripe.tools.bag_export import ExportOptions, export
    from polarstripe.tools.bag_import import import_ros2
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    _launch_ok(sim_run)
    tmp, bag = sim_run["tmp"], sim_run["bag"]
    with BagReader(bag) as b:
        frames = {log: m.image for _, log, m in b.messages(["/rig/camera/frame"])}
    assert frames
    export(bag, tmp / "ros2", "ros2", ExportOptions(progress=False))
    export(bag, tmp / "run.foxglove.mcap", "foxglove", ExportOptions(progress=False))
    seen, tf = 0, 0
    with AnyReader([tmp / "ros2"], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        for conn, ts, raw in r.messages():
            m = r.deserialize(raw, conn.msgtype)
            tf += conn.topic == "/tf_static"
            if conn.topic == "/rig/camera/frame/image":
                assert np.array_equal(m.data.view("<u2").reshape(m.height, m.width), frames[ts])
                seen += 1
    assert seen == len(frames) and tf >= 1
    import_ros2(tmp / "ros2", tmp / "imported.mcap", progress=False)
    # the imported bag through launch/replay.toml: the compositor makes every method's composite
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp / "runs_replay")}
    r = subprocess.run([sys.executable, "-m", "polarstripe", "launch", str(ROOT / "launch" / "replay.toml"),
                        "--once", f"bag={tmp / 'imported.mcap'}", f"out={tmp / 'replayed'}", "rate=4",
                        "resolution=96x72", "stripes=8",  # the planner plans the live run's rig
                        "topics=camera/frame,emitter/scan", "dark_offset_dn=64.0"],
                       cwd=tmp, env=env, capture_output=True, text=True, timeout=150)
    assert r.returncode == 0, r.stderr[-3000:]
    metrics = json.loads((tmp / "replayed" / "metrics.json").read_text())
    live = json.loads((tmp / "out" / "metrics.json").read_text())
    assert set(metrics) == set(live) and {"flood", "stripes", "hf_separation"} <= set(live)
    assert all(metrics[m]["frames"] == live[m]["frames"] for m in live)
