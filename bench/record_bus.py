"""``polarstripe bench record``'s rows over the bus: ``polarstripe record`` in its own process, subscribed
to a publisher in this process over ipc (bench/record.py says what is measured and how)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import zmq
from polarstripe.bench.proc_cpu import process_cpu
from polarstripe.msgs import Frame
from polarstripe.runtime.bag_reader import BagReader
from polarstripe.runtime.bus import PubSocket
from polarstripe.runtime.graph import write_graph


class _WatchedPub(PubSocket):
    """The bench's publisher socket, an XPUB: it sees the recorder's subscription arrive, so no frame is
    sent before (ZeroMQ drops those) however long the recorder takes to start."""

    def __init__(self, endpoint: str):  # PubSocket's, with XPUB for PUB
        self.socket = zmq.Context.instance().socket(zmq.XPUB)
        self.socket.linger = 0
        self.socket.sndhwm = 100_000
        self.socket.bind(endpoint)
        self.endpoint, self._topics = endpoint, {}

    def wait_subscribed(self, topic: str, proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and proc.poll() is None:
            if self.socket.poll(100) and self.socket.recv() == b"\x01" + topic.encode():
                return
        raise RuntimeError(f"the recorder did not subscribe to {topic} (exit code {proc.poll()})")


def over_bus(
    tmp: Path,
    frames: list[Frame],
    prepare: Callable[[], None],
    *,
    compression: str = "none",
    rate: float | None = None,
    recorder_args: tuple[str, ...] = (),
) -> dict:
    """``polarstripe record`` in its own process; once it has subscribed and started, this process calls
    ``prepare`` (memory warm or cold) and publishes ``frames`` (paced at ``rate``, else as fast as it can).
    The recorder's rate is its count over its first-to-last receive time; its CPU and the sender's ZeroMQ
    I/O thread's come from /proc."""
    ep = f"ipc://{tmp}/bench-cam.pub"
    graph = {
        "launch": "bench",
        "namespace": "/rig",
        "pid": os.getpid(),
        "run_dir": str(tmp),
        "nodes": {"cam": {"module": "bench", "pub": ep, "srv": ""}},
        "topics": {"/rig/camera/frame": {"type": "frame", "publishers": ["cam"], "subscribers": []}},
    }
    write_graph(tmp / "graph.json", graph)
    bag = tmp / f"bus-{compression}.mcap"
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp / "runs")}
    command = [sys.executable, "-m", "polarstripe", "record", "-o", str(bag), "--graph"]
    command.append(str(tmp / "graph.json"))
    with _WatchedPub(ep) as ps:
        pub = ps.publisher("/rig/camera/frame", Frame)
        proc = subprocess.Popen(
            [*command, "--compression", compression, *recorder_args],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        ps.wait_subscribed("/rig/camera/frame", proc)
        time.sleep(0.5)  # the recorder's start-up is over
        prepare()
        (rec0, flt0), (io0, _) = process_cpu(proc.pid), process_cpu(prefix="ZMQbg")
        t0 = time.perf_counter()
        for k, f in enumerate(frames):
            if rate:
                wait = t0 + k / rate - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            pub.publish(f, stamp_ns=time.time_ns())
        sent_s = time.perf_counter() - t0
        last = -1
        while (size := bag.stat().st_size if bag.exists() else 0) != last:  # until the recorder has caught up
            last = size
            time.sleep(1.0)
        (rec1, flt1), (io1, _) = process_cpu(proc.pid), process_cpu(prefix="ZMQbg")
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=300)
    if proc.returncode:
        raise RuntimeError(f"recorder failed: {err.strip().splitlines()[-1:]}")
    with BagReader(bag) as b:
        t = b.topics["/rig/camera/frame"]
        gaps = int(b.metadata["recording"]["gaps"])
        lags = [(log - m.header.stamp_ns) / 1e9 for _, log, m in b.messages()] if rate else [0.0]
        size = b.size
    bag.unlink()
    return {
        "recorded": t.count,
        "sent": len(frames),
        "gaps": gaps,
        "s": (t.last_ns - t.first_ns) / 1e9,
        "fps": (t.count - 1) / max((t.last_ns - t.first_ns) / 1e9, 1e-9),
        "offered_fps": len(frames) / sent_s,
        "lag_p99_s": float(np.percentile(lags, 99)),
        "lag_max_s": float(max(lags)),
        "bytes": size,
        "cpu_s": rec1 - rec0 + io1 - io0,  # the recorder's threads and the sender's I/O thread
        "cpu_recorder_s": rec1 - rec0,
        "faults": flt1 - flt0,
    }
