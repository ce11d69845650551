"""``polarstripe bench record``: how fast the recorder writes 1280×1024 uint16 frames, beside the disk.

Measured in one run, on the file system of ``--dir`` (default: the system temp dir):

* **plain write** — the same payload bytes (the frames' packed messages) with the recorder's file API (an
  unbuffered file, one ``os.writev`` per ``--chunk-size`` bytes of whole payloads, as ``BagWriter`` writes a
  chunk), then ``fsync``: the limit of this disk (its page cache, really, for a short run; the ``fsync``
  time is reported apart);
* **BagWriter** — :class:`~polarstripe.runtime.bag.BagWriter` in this process (no bus), uncompressed
  and zstd, beside the peer, ``mcap.Writer`` with the same payloads (it copies each payload three times);
* **recorder over the bus** (bench/record_bus.py) — ``polarstripe record`` in its own process (a fresh one
  per run, ``--chunk-size`` and ``--queue`` passed on; the median of ``--repeats`` runs for the two
  uncompressed as-fast-as-sent rows), subscribed (``mode="all"``) to a
  publisher in this process over ipc (an XPUB socket: nothing is sent before the subscription has arrived):
  frames sent as fast as the publisher can (the recorder's sustained rate is the count over its
  first-to-last receive time), and paced at ``--rate`` (default 100 frames/s: no gap, every frame written,
  and how far behind the recorder ran). The ``via`` column: ``zmq``, every byte through the socket, or
  ``shm``, the frames through the publisher's shared-memory ring (``--transport``, runtime/shm_bus.py; the
  ring holds the whole burst, as the socket's queue does, and is made before the memory is prepared, as a
  running publisher's is). The as-fast-as-sent rows run ``--repeats`` alternating rounds (zmq and shm,
  warm and cold in each round) and print each round's ratio to the plain write's median;
* **export** — ``polarstripe bag export`` of a recording of the frames (a simulator launch's metadata, so
  camera info and tf go along) to a ROS 2 bag and to a Foxglove MCAP, in frames per second and as a ratio
  to reading the same bag alone (``BagReader.messages``, every frame decoded); warm, the median of
  ``--repeats``; target: ratio ≥ 0.5.

Memory **warm** or **cold**: writing into the page cache (and receiving into fresh buffers) costs what
the kernel pays to hand out a page. Pages freed a moment ago are cheap; on a virtual machine that returns
freed memory to its host (virtio-balloon free page reporting, ~2 s after the free) a page that has been free
for a while faults on the host too, and the same write runs ~5× slower (measured on the 2-CPU development
VM: a plain write of 2.6 MB frames at ~1800 frames/s warm, ~300 cold). So every row says which it
measured, and ``vs plain`` compares it with the plain write of the same kind: **warm** rows run right after
writing and deleting a scratch file twice the payload's size (:func:`_warm`; over the bus the publisher
does it just before it sends), **cold** rows after ``--cold-pause`` seconds of idle (what a recorder meets
when a burst of frames follows a quiet spell). On bare metal the two agree.

Every row also gives the **CPU** it cost per frame (user + system; in this process the writing thread's,
over the bus the recorder process's threads and the sender's, its publishing thread, which copies into the
ring with shm, and its ZeroMQ I/O thread, which copies into the socket with zmq, from /proc) and the
**minor page faults** per frame (over the bus: the recorder's, i.e. receive buffers in fresh pages, or with
shm the ring's pages it maps at its first frame). On a
busy machine the frame rates follow the scheduler; the CPU per frame says what each path costs. Neither row
counts the final ``fsync`` (reported apart for the in-process rows; the recorder's comes after its last
message).

The frames are 12-bit noise with a stripe (so zstd sees realistic entropy). Numbers vary with what else runs
on the machine; compare rows of one run.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType, Writer
from polarstripe.bench.proc_cpu import thread_cpu
from polarstripe.bench.record_bus import over_bus
from polarstripe.bench.record_export import export_rows
from polarstripe.msgs import Frame, decode, encode, json_schema, pack
from polarstripe.runtime.bag import BagWriter, write_buffers
from polarstripe.tools.record import parse_bytes

TRANSPORTS = ("zmq", "shm")  # how the frames reach the recorder: through the socket, through shared memory


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=150, help="frames per measurement (default 150)")
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=1024)
    parser.add_argument("--rate", type=float, default=100.0, help="paced rate over the bus [frames/s]")
    parser.add_argument("--dir", default=None, help="where to write (default: the system temp dir)")
    parser.add_argument("--no-bus", action="store_true", help="skip the over-the-bus measurements")
    parser.add_argument("--no-export", action="store_true", help="skip the bag export measurements")
    parser.add_argument(
        "--repeats", type=int, default=3, help="runs of each in-process and uncompressed bus row; the median"
    )
    parser.add_argument(
        "--cold-pause", type=float, default=3.0, help="idle time before a cold measurement [s] (default 3)"
    )
    parser.add_argument(
        "--chunk-size", default="1M", metavar="SIZE",
        help="the recorder's and BagWriter's chunk size, the plain write's bytes per writev (default 1M)",
    )
    parser.add_argument(
        "--queue", type=int, default=None, metavar="N", help="the recorder's receive queue (default: its own)"
    )


def _frames(n: int, h: int, w: int) -> list[Frame]:
    rng = np.random.default_rng(0)
    base = rng.integers(0, 4096, size=(8, h, w), dtype=np.uint16)
    out = []
    for k in range(n):
        img = base[k % 8].copy()
        img[:, (k * 37) % w : (k * 37) % w + w // 30] |= 0x0800  # a lit stripe
        # as the recorder gets it: decoded from wire frames (arrays are views of the received buffers)
        out.append(
            decode(
                [
                    bytes(b) if i == 0 else memoryview(b)
                    for i, b in enumerate(encode(Frame(image=img, exposure_s=0.008, step=k)))
                ]
            )
        )
    return out


def _warm(directory: Path, nbytes: int) -> None:
    """Write ``nbytes`` of zeros to a scratch file and delete it: that much page-cache memory is freed just
    now, so the next writes (and receive buffers) get warm pages (see the module docstring)."""
    block = bytes(16 << 20)
    path = directory / "warm.scratch"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        for _ in range(max(1, -(-nbytes // len(block)))):
            os.write(fd, block)
    finally:
        os.close(fd)
        path.unlink()


def _plain(path: Path, blobs: list[bytes], chunk_size: int) -> dict:
    """The same bytes with BagWriter's file API: an unbuffered file, one ``os.writev`` per ``chunk_size``
    bytes of whole payloads (as the recorder writes its chunks: a payload past the size closes one)."""
    c0, t0 = thread_cpu(), time.perf_counter()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        group, size = [], 0
        for b in blobs:
            group.append(b)
            size += len(b)
            if size >= chunk_size:
                write_buffers(fd, group)
                group, size = [], 0
        write_buffers(fd, group)
        t1, cpu = time.perf_counter(), thread_cpu(c0)
        os.fsync(fd)
    finally:
        os.close(fd)
    return {"s": t1 - t0, "fsync_s": time.perf_counter() - t1, "bytes": os.path.getsize(path), **cpu}


def _bagwriter(path: Path, frames: list[Frame], compression: str, chunk_size: int) -> dict:
    c0, t0 = thread_cpu(), time.perf_counter()
    w = BagWriter(path, compression=compression, chunk_size=chunk_size).start()
    for f in frames:
        w.add_message("/rig/camera/frame", f)
    w.finish(fsync=False)
    t1, cpu = time.perf_counter(), thread_cpu(c0)
    fd = os.open(path, os.O_RDONLY)
    os.fsync(fd)
    os.close(fd)
    return {"s": t1 - t0, "fsync_s": time.perf_counter() - t1, "bytes": os.path.getsize(path), **cpu}


def _mcap_writer(path: Path, frames: list[Frame], blobs: list[bytes]) -> dict:
    c0, t0 = thread_cpu(), time.perf_counter()
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE, chunk_size=1 << 20)
        w.start()
        sid = w.register_schema("polarstripe/frame", "jsonschema", json.dumps(json_schema(Frame)).encode())
        cid = w.register_channel("/rig/camera/frame", "msgpack", sid)
        for f, b in zip(frames, blobs, strict=True):
            w.add_message(cid, time.time_ns(), b, f.header.stamp_ns)
        w.finish()
        fh.flush()
        t1, cpu = time.perf_counter(), thread_cpu(c0)
        os.fsync(fh.fileno())
    return {"s": t1 - t0, "fsync_s": time.perf_counter() - t1, "bytes": os.path.getsize(path), **cpu}


def run(
    n: int,
    h: int,
    w: int,
    rate: float,
    directory: str | None,
    bus: bool,
    *,
    repeats: int = 3,
    cold_pause_s: float = 3.0,
    export: bool = True,
    chunk_size: int = 1 << 20,
    queue: int | None = None,
) -> dict:
    frames = _frames(n, h, w)
    blobs = [pack(f) for f in frames]
    total = sum(len(b) for b in blobs)
    out: dict = {"frames": n, "frame_bytes": len(blobs[0]), "width": w, "height": h, "rows": {}}
    out["chunk_size"] = chunk_size
    with tempfile.TemporaryDirectory(dir=directory) as d:
        tmp = Path(d)
        rows = out["rows"]
        warm = lambda: _warm(tmp, 2 * total)  # noqa: E731
        cold = lambda: time.sleep(cold_pause_s)  # noqa: E731
        in_process = (
            ("plain write", "warm", warm, lambda p: _plain(p, blobs, chunk_size)),
            ("plain write", "cold", cold, lambda p: _plain(p, blobs, chunk_size)),
            ("BagWriter none", "warm", warm, lambda p: _bagwriter(p, frames, "none", chunk_size)),
            ("BagWriter none", "cold", cold, lambda p: _bagwriter(p, frames, "none", chunk_size)),
            ("BagWriter zstd", "warm", warm, lambda p: _bagwriter(p, frames, "zstd", chunk_size)),
            ("mcap.Writer none (peer)", "warm", warm, lambda p: _mcap_writer(p, frames, blobs)),
        )
        for name, memory, prepare, fn in in_process:  # the median of `repeats` runs
            runs = []
            for _ in range(repeats):
                prepare()
                runs.append(fn(tmp / "out.bin"))
                (tmp / "out.bin").unlink()
            row = rows[f"{name} ({memory})"] = {**sorted(runs, key=lambda r: r["s"])[len(runs) // 2]}
            row["memory"], row["fps"], row["fps_runs"] = memory, n / row["s"], [n / r["s"] for r in runs]
        if export:
            out["export"] = export_rows(tmp, frames, repeats, warm)
        args = ("--chunk-size", str(chunk_size), *(() if queue is None else ("--queue", str(queue))))
        if bus:  # the target rows: `repeats` alternating rounds of both transports, warm and cold; medians
            got: dict = {}
            for _ in range(repeats):
                for memory in ("warm", "cold"):
                    for via in TRANSPORTS:
                        got.setdefault(("recorder over bus, none, max", via, memory), []).append(over_bus(
                            tmp, frames, warm if memory == "warm" else cold, recorder_args=args, transport=via
                        ))
            for name, comp, pace, memory in (
                ("recorder over bus, zstd, max", "zstd", None, "warm"),
                (f"recorder over bus, none, {rate:g}/s", "none", rate, "cold"),
            ):
                got[(name, "shm", memory)] = [over_bus(tmp, frames, warm if memory == "warm" else cold,
                                                       compression=comp, rate=pace, recorder_args=args,
                                                       transport="shm")]
            for (name, via, memory), runs in got.items():
                rows[f"{name} ({memory}, {via})"] = {
                    **sorted(runs, key=lambda r: r["fps"])[len(runs) // 2],
                    "gaps": max(r["gaps"] for r in runs),
                    "recorded": min(r["recorded"] for r in runs),
                    "fps_runs": [r["fps"] for r in runs],
                    "memory": memory,
                }
    rows = out["rows"]
    plain = {"warm": rows["plain write (warm)"]["fps"], "cold": rows["plain write (cold)"]["fps"]}
    plain_cpu = {m: rows[f"plain write ({m})"]["cpu_s"] for m in ("warm", "cold")}
    for r in rows.values():
        r["MB_s"] = r["fps"] * len(blobs[0]) / 1e6
        r["vs_plain"] = r["fps"] / plain[r["memory"]]
        r["cpu_ms_per_frame"] = 1e3 * r["cpu_s"] / n
        base = plain_cpu[r["memory"]]
        r["cpu_vs_plain"] = r["cpu_s"] / base if base > 0 else float("nan")
    out["payload_MB"] = total / 1e6
    for r in rows.values():
        r["vs_plain_runs"] = [f / plain[r["memory"]] for f in r["fps_runs"]]
    if bus:
        out["target"] = {"writer_within_80pct_of_plain": rows["BagWriter none (warm)"]["vs_plain"] >= 0.8}
        for via in TRANSPORTS:
            warm_r, cold_r = (rows[f"recorder over bus, none, max ({m}, {via})"] for m in ("warm", "cold"))
            paced = rows[f"recorder over bus, none, {rate:g}/s (cold, shm)"]
            out["target"][via] = {
                "uncompressed_fps_ge_100": min(warm_r["fps"], cold_r["fps"]) >= 100,
                "no_gap": all(r["gaps"] == 0 for r in (warm_r, cold_r, paced))
                and paced["recorded"] == paced["sent"],
                "bus_within_80pct_of_plain": warm_r["vs_plain"] >= 0.8,
                "bus_within_80pct_of_plain_cold": cold_r["vs_plain"] >= 0.8,
            }
    return out


def main(args: argparse.Namespace) -> int:
    res = run(
        args.frames,
        args.height,
        args.width,
        args.rate,
        args.dir,
        not args.no_bus,
        repeats=args.repeats,
        cold_pause_s=args.cold_pause,
        export=not args.no_export,
        chunk_size=parse_bytes(args.chunk_size),
        queue=args.queue,
    )
    if args.json:
        print(json.dumps(res))
        return 0
    print(
        f"recording {res['frames']} frames {res['width']}×{res['height']} uint16 "
        f"({res['frame_bytes'] / 1e6:.2f} MB each, {res['payload_MB']:.0f} MB), chunks of "
        f"{res['chunk_size'] / 2**20:g} MiB"
    )
    print(
        f"{'writer (memory)':<36} {'via':<4} {'frames/s':>9} {'MB/s':>8} {'vs plain':>9} {'size/raw':>9} "
        f"{'CPU ms/fr':>9} {'faults/fr':>9}  notes"
    )
    raw = res["payload_MB"] * 1e6
    for name, r in res["rows"].items():
        spread = (f"{min(r['fps_runs']):.0f}–{max(r['fps_runs']):.0f}/s ({min(r['vs_plain_runs']):.2f}–"
                  f"{max(r['vs_plain_runs']):.2f} of plain) over {len(r['fps_runs'])}; ")
        notes = (spread if len(r["fps_runs"]) > 1 else "") + (
            f"fsync {r['fsync_s']:.2f} s after"
            if "fsync_s" in r
            else (
                f"{r['recorded']}/{r['sent']} written, {r['gaps']} gaps, offered {r['offered_fps']:.0f}/s"
                + (f", lag p99 {r['lag_p99_s'] * 1e3:.0f} ms" if "max" not in name else "")
            )
        )
        cells = (
            f"{r['fps']:>9.0f} {r['MB_s']:>8.0f} {r['vs_plain']:>8.0%} {r['bytes'] / raw:>9.2f} "
            f"{r['cpu_ms_per_frame']:>9.2f} {r['faults'] / res['frames']:>9.0f}"
        )
        via = r.get("transport", "")
        print(f"{name.replace(f', {via})', ')'):<36} {via or '-':<4} {cells}  {notes}")
    print(
        "vs plain: against the plain write with memory in the same state (warm or cold: module docstring); "
        "CPU: the writing thread, or over the bus the recorder's threads and the sender's (publishing, I/O); "
        "faults: minor page faults (the recorder's, over the bus)"
    )
    if "export" in res:
        e = res["export"]
        w = res["rows"]["BagWriter none (warm)"]["fps"]
        print(f"bag export (warm): reading the bag alone {e['read_fps']:.0f} frames/s; to ROS 2 "
              f"{e['ros2_fps']:.0f} frames/s ({e['ros2_ratio']:.2f} of reading, {e['ros2_fps'] / w:.2f} of "
              f"BagWriter's write), to Foxglove {e['foxglove_fps']:.0f} frames/s ({e['foxglove_ratio']:.2f}, "
              f"{e['foxglove_fps'] / w:.2f}); target ratio >= 0.5: "
              + ("yes" if e["target_ratio_ge_0_5"] else "NO"))
    if "target" in res:
        t = res["target"]
        yes = {True: "yes", False: "NO"}
        print(f"target: the writer within 80% of the plain write {yes[t['writer_within_80pct_of_plain']]}")
        for via in TRANSPORTS:
            v = t[via]
            print(
                f"target over {via}: ≥100 frames/s uncompressed {yes[v['uncompressed_fps_ge_100']]}, "
                f"no gap {yes[v['no_gap']]}; end to end within 80% of the plain write "
                f"{yes[v['bus_within_80pct_of_plain']]} warm, {yes[v['bus_within_80pct_of_plain_cold']]} cold"
                + (" (the socket adds two copies of every frame: into the kernel and out of it)"
                   if via == "zmq" else
                   " (one copy into the ring, in the sender; the recorder writes from it)")
            )
    return 0
