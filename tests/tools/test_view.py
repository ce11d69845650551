"""Looking at a rig: the contact sheet (from a bag and live), and the Foxglove bridge on loopback (skipped
when the optional ``foxglove-sdk`` is absent)."""

import base64
import json
import os
import socket
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from polarstripe.msgs import Composite, Frame, Header, pack, unpack
from polarstripe.tools.bag import BagWriter
from polarstripe.runtime.bus import PubSocket
from polarstripe.tools.view import ViewError, contact_sheet, latest_from_bag, latest_live, tiles


def _frame(k: int) -> Frame:
    img = np.full((24, 32), 100 * k, np.uint16)
    img[:, 4 * k : 4 * k + 4] = 4000  # stripe k
    return Frame(image=img, exposure_s=0.01, step=k, pattern=f"stripe:{k}/4", polarizer_deg=0.0, scan_id=2)


def _composite(method: str, value: float) -> Composite:
    return Composite(
        images={"composite": np.full((24, 32), value, np.float32), "saturated": np.zeros((24, 32), np.uint8)},
        method=method,
        scan_id=2,
    )


def _png_size(path) -> tuple[int, int]:
    data = open(path, "rb").read(24)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def test_contact_sheet_of_a_bag_has_the_latest_frame_and_each_method(tmp_path):
    bag = tmp_path / "b.mcap"
    with BagWriter(bag) as w:
        for k in range(4):
            w.add_message("/rig/camera/frame", _frame(k))
        w.add_message("/rig/compositor/composite", _composite("stripes", 1.0))
        w.add_message("/rig/compositor/composite", _composite("flood", 2.0))
        w.add_message("/rig/compositor/composite", _composite("stripes", 3.0))  # a later stripes scan
    latest = latest_from_bag(bag)
    assert set(latest) == {
        "/rig/camera/frame",
        "/rig/compositor/composite [stripes]",
        "/rig/compositor/composite [flood]",
    }
    assert latest["/rig/camera/frame"].step == 3
    assert latest["/rig/compositor/composite [stripes]"].images["composite"][0, 0] == 3.0
    items = tiles(latest)
    assert len(items) == 3  # the frame and two composites; saturation masks are not shown
    assert "stripe:3/4" in items[0][0]
    r = subprocess.run(
        [sys.executable, "-m", "polarstripe", "view", "--bag", str(bag), "-o", str(tmp_path / "sheet.png")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    w, h = _png_size(tmp_path / "sheet.png")
    assert w > h > 100  # three tiles in a row


def test_contact_sheet_errors(tmp_path):
    with pytest.raises(ViewError, match="nothing to show"):
        contact_sheet([], tmp_path / "x.png")
    with BagWriter(tmp_path / "empty.mcap"):
        pass
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "polarstripe",
            "view",
            "--bag",
            str(tmp_path / "empty.mcap"),
            "-o",
            str(tmp_path / "s.png"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "nothing to show" in r.stderr and not (tmp_path / "s.png").exists()


def test_live_view_takes_the_newest_frame(tmp_path):
    ep = f"ipc://{tmp_path}/cam.pub"
    graph = {
        "launch": "t",
        "namespace": "/rig",
        "nodes": {"cam": {"pub": ep}},
        "topics": {
            "/rig/camera/frame": {"type": "frame", "publishers": ["cam"], "subscribers": []},
            "/rig/log": {"type": "log", "publishers": ["cam"], "subscribers": []},
        },
    }
    sent = []
    with PubSocket(ep) as ps:
        pub = ps.publisher("/rig/camera/frame", Frame)
        import threading

        def send():  # for 2 s, while the view collects for 3 s
            t0 = time.monotonic()
            while time.monotonic() - t0 < 2.0:
                pub.publish(_frame(len(sent) % 6))
                sent.append(len(sent) % 6)
                time.sleep(0.05)

        t = threading.Thread(target=send)
        t.start()
        latest = latest_live(graph, 3.0)
        t.join()
    assert list(latest) == ["/rig/camera/frame"] and latest["/rig/camera/frame"].step == sent[-1]
    with pytest.raises(ViewError, match="no frame or composite arrived within 0.2 s"):
        latest_live(graph, 0.2)


# ---- Foxglove bridge ---------------------------------------------------------------------------------------
class _WsClient:
    """The smallest WebSocket client that speaks to the Foxglove server: handshake, JSON text, binary."""

    def __init__(self, port: int):
        self.s = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.adv: dict[str, dict] = {}  # topic -> channel, from every advertise seen
        key = base64.b64encode(os.urandom(16)).decode()
        self.s.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                "Sec-WebSocket-Protocol: foxglove.sdk.v1, foxglove.websocket.v1\r\n\r\n"
            ).encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.s.recv(1)
        assert head.startswith(b"HTTP/1.1 101"), head

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
        head = bytes([0x81]) + (
            bytes([0x80 | len(data)])
            if len(data) < 126
            else bytes([0x80 | 126]) + struct.pack(">H", len(data))
        )
        self.s.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def until(self, pred, timeout_s=10.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            msg = self.recv()
            if pred(msg):
                return msg
        raise AssertionError("not received")


def test_foxglove_bridge_serves_msgpack_and_raw_images_on_loopback():
    pytest.importorskip("foxglove")
    from polarstripe.tools.foxglove_bridge import FoxgloveBridge, raw_image_fields
    from polarstripe.runtime.testing import MockBus

    bus = MockBus()
    bus.graph = {
        "launch": "t",
        "topics": {
            "/rig/camera/frame": {"type": "frame"},
            "/rig/compositor/composite": {"type": "composite"},
        },
    }
    node = FoxgloveBridge("foxglove", namespace="/rig", params={"port": 0}, bus=bus)
    node.setup()
    try:
        assert node.port > 0
        ws = _WsClient(node.port)
        ws.until(lambda m: "/rig/camera/frame" in ws.adv)
        ch = ws.adv["/rig/camera/frame"]
        assert ch["encoding"] == "msgpack" and ch["schemaEncoding"] == "jsonschema"
        assert json.loads(ch["schema"])["title"] == "polarstripe/frame"
        ws.send_json({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": ch["id"]}]})
        sent = _frame(1)
        sent = Frame(
            **{n: getattr(sent, n) for n, _ in Frame.FIELDS}, header=Header(stamp_ns=123456789, seq=4)
        )
        ws.s.settimeout(0.3)
        data = None
        for _ in range(40):  # until the server has applied the subscription
            node.forward("/rig/camera/frame", sent)
            try:
                data = ws.until(lambda m: isinstance(m, bytes) and m[0] == 1, timeout_s=0.3)
                break
            except (TimeoutError, AssertionError):
                continue
        assert data is not None, "no message data"
        sub_id, log_time = struct.unpack("<IQ", data[1:13])
        assert sub_id == 7 and log_time == 123456789
        assert data[13:] == pack(sent, topic="/rig/camera/frame")
        got = unpack(data[13:])
        assert np.array_equal(got.image, sent.image)
        # the image channel for the image panel is advertised once a frame was logged
        ws.s.settimeout(10)
        if "/rig/camera/frame/image" not in ws.adv:
            ws.until(lambda m: "/rig/camera/frame/image" in ws.adv)
        assert ws.adv["/rig/camera/frame/image"]["schemaName"] == "foxglove.RawImage"
    finally:
        node.teardown()
    f = raw_image_fields(sent.image)
    assert (f["width"], f["height"], f["encoding"], f["step"]) == (32, 24, "mono16", 64)
    assert np.array_equal(np.frombuffer(f["data"], "<u2").reshape(24, 32), sent.image)
