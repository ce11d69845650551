"""``polarstripe bench record``'s export rows: frames per second of reading a bag alone and of exporting it to
a ROS 2 bag and to a Foxglove MCAP (bench/record.py)."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

from polarstripe.msgs import Frame
from polarstripe.runtime.bag import BagWriter
from polarstripe.runtime.bag_reader import BagReader


def export_rows(tmp: Path, frames: list[Frame], repeats: int, warm) -> dict:
    """Frames per second of reading a bag of ``frames`` alone and of exporting it (ROS 2, Foxglove)."""
    from polarstripe.tools.bag_export import ExportOptions, export

    src = tmp / "export-src.mcap"
    graph = {"nodes": {"simulator": {"module": "polarstripe.nodes.simulator", "params": {}}}}
    with BagWriter(src) as w:
        w.add_metadata("launch", {"launch": "bench", "namespace": "/rig", "graph": json.dumps(graph)})
        for k, f in enumerate(frames):
            w.add_message("/rig/camera/frame", f, log_time_ns=1_800_000_000_000_000_000 + k * 10_000_000)

    def read(_out: Path) -> None:
        with BagReader(src) as b:
            for _ in b.messages():
                pass

    def exporter(fmt: str):
        return lambda out: export(src, out, fmt, ExportOptions(progress=False))

    fps = {}
    for name, fn in (("read", read), ("ros2", exporter("ros2")), ("foxglove", exporter("foxglove"))):
        times = []
        for _ in range(repeats):
            warm()
            out = tmp / f"export-{name}"
            t0 = time.perf_counter()
            fn(out)
            times.append(time.perf_counter() - t0)
            shutil.rmtree(out, ignore_errors=True) if out.is_dir() else out.unlink(missing_ok=True)
        fps[name] = len(frames) / sorted(times)[len(times) // 2]
    src.unlink()
    return {
        "read_fps": fps["read"],
        **{f"{k}_fps": fps[k] for k in ("ros2", "foxglove")},
        **{f"{k}_ratio": fps[k] / fps["read"] for k in ("ros2", "foxglove")},
        "target_ratio_ge_0_5": min(fps["ros2"], fps["foxglove"]) / fps["read"] >= 0.5,
    }  # the write of the same bytes alone: the row "BagWriter none (warm)"
