"""``polarstripe bench transport``: the bus between two processes vs raw pyzmq vs memcpy, in one run.

For each payload (a 1280x1024 uint16 frame = 2.62 MB, 64 KiB, 100 B) and each transport:

* **bus**: ``PubSocket``/``Subscriber(mode="all")`` carrying a :class:`~polarstripe.msgs.Frame` whose
``image`` is
  the payload (full validation on receive, a read-only zero-copy view).
* **pyzmq**: raw PUB/SUB ``send_multipart([topic, msgpack(seq, t, flag, dtype, shape), ndarray],
copy=False)``,
  ``recv_multipart(copy=False)`` and ``np.frombuffer``: the floor any layer on pyzmq adds to.
* **pyzmq-parts**: the same raw pyzmq, sent and received part by part (``send(…, SNDMORE)``,
  ``recv(copy=False)`` and ``Frame.more``), which is how the bus does it: ``send_multipart`` and
  ``recv_multipart`` cost ~1 µs per part in checks and ``getsockopt(RCVMORE)``. The bus's own cost is its
  difference to this row.
* **memcpy**: ``np.copyto`` of the same buffer in one process (the physical limit; cache-hot).

Method: latency = paced sends, one-way = receiver's ``perf_counter_ns``
(CLOCK_MONOTONIC, valid across processes) after reading one element, minus the sender's stamp.
Throughput = sends for ``--seconds`` limited by a window of un-acknowledged messages (the receiver acks
how many it has received over a side PUSH/PULL channel), so a lossy path cannot count messages it dropped.
``lost`` = sent - received over both phases (must be 0: ``all`` mode never drops silently). Both
transports use ipc and the same HWMs. Figures are medians over ``--rounds`` rounds run in alternating order.

The two processes (each transport's sender and receiver, the measuring loop) are in
:mod:`polarstripe.bench.transport_peers`; this module runs them, adds memcpy and the in-process layer costs,
and prints the table.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
import timeit

import msgpack
import numpy as np
from polarstripe.bench.transport_peers import HWM, SIZES, TOPIC, TRANSPORTS, _run_transport
from polarstripe.errors import PolarstripeError
from polarstripe.msgs import Frame, decode, encode

__all__ = ["HELP", "HWM", "SIZES", "TOPIC", "TRANSPORTS", "configure", "main", "run"]

HELP = "bus throughput and latency vs raw pyzmq and memcpy"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=1.0, help="throughput phase per size and transport")
    parser.add_argument("--rounds", type=int, default=3, help="rounds (alternating order); medians are shown")
    parser.add_argument(
        "--quick", action="store_true", help="short run (0.5 s phases, fewer latency samples)"
    )
    parser.add_argument(
        "--sizes", default=",".join(SIZES), help="comma-separated subset of: " + ", ".join(SIZES)
    )


def _memcpy(size_names):
    out = {}
    for name in size_names:
        shape, dtype, *_ = SIZES[name]
        src = (np.arange(int(np.prod(shape))) % 251).astype(dtype).reshape(shape)
        dst = np.empty_like(src)
        reps = max(50, int(2e8 // max(src.nbytes, 1000)) // 10)
        per = []
        for _ in range(3):
            t0 = time.perf_counter_ns()
            for _ in range(reps):
                np.copyto(dst, src)
            per.append((time.perf_counter_ns() - t0) / reps)
        samples = []
        for _ in range(200):
            t0 = time.perf_counter_ns()
            np.copyto(dst, src)
            samples.append(time.perf_counter_ns() - t0)
        best = min(per) / 1e9
        out[name] = {
            "msgs_per_s": 1 / best,
            "MB_per_s": src.nbytes / best / 1e6,
            "p50_us": statistics.median(samples) / 1e3,
            "p99_us": float(np.percentile(samples, 99)) / 1e3,
            "lost": 0,
            "tx_cpu_us": best * 1e6,
            "rx_cpu_us": 0.0,
        }
    return out


def _median(results: list[dict]) -> dict:
    """Median of each figure over rounds; ``lost`` is summed (any loss must show)."""
    out = {k: float(np.median([r[k] for r in results])) for k in results[0]}
    for k in ("lost", "sent", "received", "latency_sent", "latency_samples"):
        out[k] = int(sum(r[k] for r in results))
    out["rounds"] = len(results)
    return out


def _layer_cost(size_names) -> dict:
    """In-process cost per message of what each layer adds around the socket (min of repeats: robust to load):
    bus = Frame() + encode on send, decode (all checks, read-only view) on receive; pyzmq = msgpack header
    pack on send, unpack + ``np.frombuffer`` on receive."""

    out = {}
    for name in size_names:
        shape, dtype, *_ = SIZES[name]
        payload = (np.arange(int(np.prod(shape))) % 251).astype(dtype).reshape(shape)
        frames = [
            bytes(f) if isinstance(f, bytes) else memoryview(f).cast("B")
            for f in encode(Frame(image=payload, exposure_s=0.0, step=0), seq=1, stamp_ns=1)
        ]
        raw = [msgpack.packb((1, 1, 0, payload.dtype.str, payload.shape)), memoryview(payload).cast("B")]

        out[name] = _layer_figures(payload, frames, raw)
    return out


def _layer_figures(payload, frames, raw) -> dict:


    def best(fn, n=2000):
        return min(timeit.repeat(fn, number=n, repeat=5)) / n * 1e6

    return {
        "bus_send_us": best(lambda: encode(Frame(image=payload, exposure_s=0.0, step=0), seq=1, stamp_ns=1)),
        "bus_recv_us": best(lambda: decode(frames, expect=Frame).image.flat[0]),
        "pyzmq_send_us": best(lambda: msgpack.packb((1, 1, 0, payload.dtype.str, payload.shape))),
        "pyzmq_recv_us": best(lambda: np.frombuffer(raw[1], dtype=msgpack.unpackb(raw[0])[3]).flat[0]),
    }


def run(seconds: float = 1.0, quick: bool = False, sizes: list[str] | None = None, rounds: int = 3) -> dict:
    """Measure everything; returns ``{size: {transport: figures}}`` (medians over rounds) with ratios."""
    sizes = sizes or list(SIZES)
    if quick:
        seconds, rounds = min(seconds, 0.5), 1
    runs: dict[str, list[dict]] = {kind: [] for kind in TRANSPORTS}
    with tempfile.TemporaryDirectory(prefix="ps-bench-") as tmp:
        for r in range(rounds):  # alternate the order: the machine's load drifts
            for kind in list(TRANSPORTS) if r % 2 == 0 else list(TRANSPORTS)[::-1]:
                runs[kind].append(_run_transport(kind, sizes, seconds, quick, tmp))
    per = {kind: {name: _median([one[name] for one in rs]) for name in sizes} for kind, rs in runs.items()}
    per["memcpy"] = _memcpy(sizes)
    table = {}
    for name in sizes:
        row = {k: per[k][name] for k in ("memcpy", "pyzmq", "pyzmq-parts", "bus")}
        m = row["memcpy"]
        for r in row.values():
            r["bw_vs_memcpy"] = r["MB_per_s"] / m["MB_per_s"]
            r["p50_vs_memcpy"] = r["p50_us"] / m["p50_us"]
        for k in ("pyzmq-parts", "bus"):
            row[k]["bw_vs_pyzmq"] = row[k]["msgs_per_s"] / row["pyzmq"]["msgs_per_s"]
            row[k]["p50_vs_pyzmq"] = row[k]["p50_us"] / row["pyzmq"]["p50_us"]
            row[k]["cpu_vs_pyzmq"] = [row[k][c] / row["pyzmq"][c] for c in ("tx_cpu_us", "rx_cpu_us")]
        parts = row["pyzmq-parts"]
        row["bus"]["cpu_vs_parts"] = [row["bus"][c] / parts[c] for c in ("tx_cpu_us", "rx_cpu_us")]
        table[name] = row
    for name, cost in _layer_cost(sizes).items():
        table[name]["layer"] = cost
    return table


def main(args: argparse.Namespace) -> int:

    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    unknown = [s for s in sizes if s not in SIZES]
    if unknown:
        raise PolarstripeError(f"--sizes: unknown size {unknown[0]!r} (choose from {', '.join(SIZES)})")
    load_before = os.getloadavg()[0]
    table = run(seconds=args.seconds, quick=args.quick, sizes=sizes, rounds=args.rounds)
    load = (load_before, os.getloadavg()[0])  # other work on the machine skews wall-clock figures
    if args.json:
        print(json.dumps({"cpus": os.cpu_count(), "load_avg_1min": load, "results": table}, indent=1))
        return 0
    rounds = next(iter(table.values()))["bus"]["rounds"]
    print(
        f"transport between two processes (ipc, {os.cpu_count()} CPUs, load average {load[0]:.1f} -> "
        f"{load[1]:.1f}), median of {rounds} round(s); "
        "ratios from this run.\nCPU us = CPU time per message in the sending / receiving process during the "
        "throughput phase (steadier than wall-clock rates on a loaded machine).\n"
    )
    head = (
        f"| {'size':<12} | {'transport':<11} | {'msgs/s':>10} | {'MB/s':>9} | {'BW/memcpy':>9} "
        f"| {'p50 us':>8} | {'p99 us':>8} | {'p50/memcpy':>10} | {'lost':>4} | {'tx CPU us':>9} "
        f"| {'rx CPU us':>9} | {'bus/pyzmq msgs/s':>16} |"
    )
    print(head)
    print("|" + "|".join("-" * (len(c)) for c in head.split("|")[1:-1]) + "|")
    for name, row in table.items():
        for k, r in row.items():
            if k == "layer":
                continue
            vs = f"{r['bw_vs_pyzmq']:.2f} (p50 {r['p50_vs_pyzmq']:.2f})" if "bw_vs_pyzmq" in r else ""
            print(
                f"| {name:<12} | {k:<11} | {r['msgs_per_s']:>10,.0f} | {r['MB_per_s']:>9,.0f} | "
                f"{r['bw_vs_memcpy']:>9.3f} | {r['p50_us']:>8.1f} | {r['p99_us']:>8.1f} | "
                f"{r['p50_vs_memcpy']:>10.1f} | {r.get('lost', 0):>4} | {r['tx_cpu_us']:>9.1f} "
                f"| {r['rx_cpu_us']:>9.1f} | {vs:>16} |"
            )
    print("\nCPU per message, bus ÷ pyzmq and bus ÷ pyzmq-parts (send / receive):")
    for name, row in table.items():
        a, b = row["bus"]["cpu_vs_pyzmq"], row["bus"]["cpu_vs_parts"]
        print(f"  {name:<12}  ÷ pyzmq {a[0]:.2f} / {a[1]:.2f}    ÷ pyzmq-parts {b[0]:.2f} / {b[1]:.2f}")
    print("\nwhat each layer adds around the socket, in-process, µs per message (min of 5 repeats):")
    for name, row in table.items():
        c = row["layer"]
        print(
            f"  {name:<12}  bus: send {c['bus_send_us']:5.1f}  receive {c['bus_recv_us']:5.1f}    "
            f"pyzmq: send {c['pyzmq_send_us']:5.1f}  receive {c['pyzmq_recv_us']:5.1f}"
        )
    return 0
