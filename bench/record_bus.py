"""``polarstripe bench record``'s rows over the bus: ``polarstripe record`` in its own process, subscribed
to a publisher in this process over ipc, with frames through the socket (``zmq``) or through the
publisher's shared-memory ring (``shm``; bench/record.py says what is measured and how)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from polarstripe.bench.proc_cpu import process_cpu, thread_cpu
from polarstripe.msgs import Frame, encode
from polarstripe.runtime.bag_reader import BagReader
from polarstripe.runtime.bus import PubSocket
from polarstripe.runtime.graph import write_graph
from polarstripe.runtime.shm_ring import slot_bytes


class _WatchedPub(PubSocket):
    """The bench's publisher socket, offering the ring form (an XPUB, ``slots`` slots: the whole burst, as
    the socket's queue holds it): it sees the recorder's subscription arrive, so no frame is sent before
    (ZeroMQ drops those) however long the recorder takes to start."""

    def __init__(self, endpoint: str, slots: int):
        super().__init__(endpoint, hwm=100_000, shm_slots=slots)
        self.shm.max_bytes = 0  # the whole burst, however large

    def wait_subscribed(self, topic: str, proc: subprocess.Popen, ring: bool,
                        timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and proc.poll() is None:
            if self.shm.wants(topic.encode())[1 if ring else 0]:
                return
            time.sleep(0.05)
        raise RuntimeError(f"the recorder did not subscribe to {topic} (exit code {proc.poll()})")


def over_bus(
    tmp: Path,
    frames: list[Frame],
    prepare: Callable[[], None],
    *,
    compression: str = "none",
    rate: float | None = None,
    recorder_args: tuple[str, ...] = (),
    transport: str = "zmq",
) -> dict:
    """``polarstripe record`` in its own process; once it has subscribed and started, this process calls
    ``prepare`` (memory warm or cold) and publishes ``frames`` (paced at ``rate``, else as fast as it can).
    The recorder's rate is its count over its first-to-last receive time; its CPU and the sender's ZeroMQ
    I/O thread's come from /proc. ``transport="shm"``: the ring is made and its pages allocated before
    ``prepare``, as a running publisher's are after its first lap, and the recorder reads frames from it."""
    ep = f"ipc://{tmp}/bench-cam.pub"
    graph = {
        "launch": "bench",
        "namespace": "/rig",
        "pid": os.getpid(),
        "run_dir": str(tmp),
        "nodes": {"cam": {"module": "bench", "pub": ep, "srv": "", "shm_slots": len(frames)}},
        "topics": {"/rig/camera/frame": {"type": "frame", "publishers": ["cam"], "subscribers": []}},
    }
    write_graph(tmp / "graph.json", graph)
    bag = tmp / f"bus-{compression}.mcap"
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp / "runs")}
    command = [sys.executable, "-m", "polarstripe", "record", "-o", str(bag), "--graph"]
    command.append(str(tmp / "graph.json"))
    with _WatchedPub(ep, len(frames)) as ps:
        pub = ps.publisher("/rig/camera/frame", Frame)
        if transport == "shm":
            ps.shm.reserve(b"/rig/camera/frame", slot_bytes([b.nbytes for b in encode(frames[0])[1:]]),
                           prefault=True)
        proc = subprocess.Popen(
            [*command, "--compression", compression, "--transport", transport, *recorder_args],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        ps.wait_subscribed("/rig/camera/frame", proc, transport == "shm")
        time.sleep(0.5)  # the recorder's start-up is over
        prepare()
        (rec0, flt0), (io0, _) = process_cpu(proc.pid), process_cpu(prefix="ZMQbg")
        t0, send0 = time.perf_counter(), thread_cpu()
        for k, f in enumerate(frames):
            if rate:
                wait = t0 + k / rate - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            pub.publish(f, stamp_ns=time.time_ns())
        sent_s, send_cpu = time.perf_counter() - t0, thread_cpu(send0)["cpu_s"]
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
        used = json.loads(b.metadata["recording"]["topics"])["/rig/camera/frame"].get("transport", "zmq")
        lags = [(log - m.header.stamp_ns) / 1e9 for _, log, m in b.messages()] if rate else [0.0]
        size = b.size
    bag.unlink()
    if used != transport:
        raise RuntimeError(f"the recorder received over {used}, not {transport}")
    return {
        "transport": used,
        "recorded": t.count,
        "sent": len(frames),
        "gaps": gaps,
        "s": (t.last_ns - t.first_ns) / 1e9,
        "fps": (t.count - 1) / max((t.last_ns - t.first_ns) / 1e9, 1e-9),
        "offered_fps": len(frames) / sent_s,
        "lag_p99_s": float(np.percentile(lags, 99)),
        "lag_max_s": float(max(lags)),
        "bytes": size,
        "cpu_s": rec1 - rec0 + io1 - io0 + send_cpu,  # the recorder's threads, the sender's (I/O, publishing)
        "cpu_recorder_s": rec1 - rec0,
        "cpu_sender_s": io1 - io0 + send_cpu,
        "faults": flt1 - flt0,
    }
