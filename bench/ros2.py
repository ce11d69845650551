"""``polarstripe bench ros2``: what the live ROS 2 bridge costs per camera frame (docs/ros2.md).

One process holds a Zenoh router on loopback (the role of ``rmw_zenohd``), the bridge node (over the mock
bus: the frames are handed to it as its subscription would) and a ROS 2-side Zenoh client subscribed to the
frame's image key. Rows, for 16-bit frames at each ``--sizes``:

* ``bridge``: :meth:`Ros2Bridge.forward` of a Frame — its views, ``sensor_msgs/Image`` + ``CameraInfo`` +
  ``FrameInfo`` in CDR, the attachment, three Zenoh puts — until the client has the image;
* ``zenoh put``: the same image's CDR bytes, built once, put on the same key (the peer: Zenoh alone);
* ``memcpy``: one copy of the pixels (the physical floor of any transport that copies once).

Frames go one at a time, each sent when the previous one has arrived (a burst would meet the puts' drop
policy, that of rmw_zenoh's keep-last publishers, and measure the drops). Each row: frames sent and received,
the median latency from the send to the client's callback (memcpy: the copy's time), the CPU ms per frame
(the whole process: router, bridge and client together, the same for every row, so the ratio of two rows is
the bridge's own cost), and the CPU as a ratio to the plain put. The load average is printed: on a shared
machine the latency holds the waits for a core.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import time

import numpy as np
from polarstripe.msgs import Frame, Header
from polarstripe.nodes.rig_views import Image
from polarstripe.nodes.ros2_bridge import Ros2Bridge
from polarstripe.nodes.ros2_zenoh import data_key
from polarstripe.runtime.mock_bus import MockBus

IMAGE = "sensor_msgs/msg/Image"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sizes", default="320x240,640x480,1280x1024",
                        help="frame sizes WxH, comma-separated")
    parser.add_argument("--frames", type=int, default=100, help="frames per row (default 100)")


def _session(mode: str, port: int, **extra):
    import zenoh

    c = zenoh.Config()
    ends = {"listen/endpoints": [f"tcp/127.0.0.1:{port}"]} if mode == "router" else {
        "connect/endpoints": [f"tcp/127.0.0.1:{port}"]}
    for k, v in {"mode": mode, "scouting/multicast/enabled": False, "scouting/gossip/enabled": False,
                 "scouting/delay": 0, **ends, **extra}.items():
        c.insert_json5(k, json.dumps(v))
    return zenoh.open(c)


def _row(name: str, frames: int, send, client: dict) -> dict:
    """Send ``frames`` one at a time with ``send()``, each after the previous one arrived (or 1 s passed):
    the median latency from the send to the client's callback, and the process CPU per frame."""
    latencies = []
    c0 = time.process_time()
    for _ in range(frames):
        before = client["count"]
        t0 = time.perf_counter()
        send()
        while client["count"] == before and time.perf_counter() - t0 < 1.0:
            time.sleep(0.0002)
        if client["count"] > before:
            latencies.append(client["last"] - t0)
    cpu = time.process_time() - c0
    return {"row": name, "sent": frames, "received": len(latencies),
            "latency_ms": 1e3 * float(np.median(latencies)) if latencies else None,
            "cpu_ms_per_frame": 1e3 * cpu / frames}


def run(sizes: list[tuple[int, int]], frames: int) -> dict:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    router = _session("router", port)
    viewer = _session("client", port)
    params = {"endpoint": f"tcp/127.0.0.1:{port}", "services": False}
    node = Ros2Bridge("ros2", namespace="/rig", params=params, bus=MockBus())
    node.setup()
    topic = "/rig/camera/frame"
    key = data_key(0, f"{topic}/image", IMAGE, node.encoder.ts.hash_rihs01(IMAGE))
    client = {"count": 0, "last": 0.0}

    def arrived(sample) -> None:
        client["count"] += 1
        client["last"] = time.perf_counter()

    viewer.declare_subscriber(key, arrived)
    raw = node.session.declare_publisher(key)
    rows = []
    try:
        for w, h in sizes:
            img = (np.arange(w * h, dtype=np.uint32).reshape(h, w) % 4096).astype(np.uint16)
            frame = Frame(image=img, exposure_s=0.01, pattern="stripe:1/4", polarizer_deg=0.0,
                          header=Header(stamp_ns=1, seq=1))
            node.forward(topic, frame)  # the publishers and cached headers exist before timing
            time.sleep(0.2)
            view = next(v for v in node.views.views(topic, 1, frame) if isinstance(v, Image))
            payload = b"".join(bytes(p) for p in node.encoder.encode(view).parts)
            out = np.empty_like(img)
            size = f"{w}x{h}"
            forward = lambda f=frame: node.forward(topic, f)  # noqa: E731
            rows.append({"size": size, **_row("bridge", frames, forward, client)})
            rows.append({"size": size, **_row("zenoh put", frames, lambda p=payload: raw.put(p), client)})
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(frames):
                np.copyto(out, img)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            rows.append({"size": size, "row": "memcpy", "sent": frames, "received": frames,
                         "latency_ms": 1e3 * wall / frames, "cpu_ms_per_frame": 1e3 * cpu / frames})
    finally:
        node.teardown()
        viewer.close()
        router.close()
    for r in rows:
        put = next(x for x in rows if x["size"] == r["size"] and x["row"] == "zenoh put")
        r["cpu_vs_put"] = r["cpu_ms_per_frame"] / put["cpu_ms_per_frame"] if put["cpu_ms_per_frame"] else None
    return {"rows": rows, "frames": frames, "load": os.getloadavg()}


def main(args: argparse.Namespace) -> int:
    sizes = [tuple(int(x) for x in s.lower().split("x")) for s in args.sizes.split(",")]
    result = run(sizes, args.frames)
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"ROS 2 bridge, 16-bit frames, {args.frames} per row; load average {result['load'][0]:.1f}")
    print(f"{'size':>10} {'row':<10} {'received':>9} {'latency ms':>11} {'CPU ms/frame':>13} "
          f"{'CPU vs put':>11}")
    for r in result["rows"]:
        ratio = f"{r['cpu_vs_put']:.2f}" if r["cpu_vs_put"] is not None else "-"
        lat = f"{r['latency_ms']:.3f}" if r["latency_ms"] is not None else "-"
        print(f"{r['size']:>10} {r['row']:<10} {r['received']:>4}/{r['sent']:<4} {lat:>11} "
              f"{r['cpu_ms_per_frame']:>13.3f} {ratio:>11}")
    return 0
