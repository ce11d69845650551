"""Looking at a rig: the contact sheet (from a bag and live). The Foxglove bridge has its own tests
(tests/nodes/test_foxglove_bridge.py)."""

import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from polarstripe.msgs import Composite, Frame
from polarstripe.runtime.bag import BagWriter
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
