"""``polarstripe record -o run.mcap [TOPIC …]``: record topics of a running launch to MCAP with the
:class:`~polarstripe.nodes.recorder.Recorder` node, run by itself.
"""

from __future__ import annotations

import argparse
import os

from polarstripe.runtime.bag import COMPRESSIONS, BagError
from polarstripe.runtime.graph import find_graph, load_graph
from polarstripe.runtime.runner import run_node

HELP = "record topics of a running launch to an MCAP file"
RECORDER = "polarstripe.nodes.recorder:Recorder"


# ---- the command -------------------------------------------------------------------------------------------
def parse_bytes(text: str) -> int:
    """``"512M"`` → 536870912; suffixes K, M, G (powers of 1024); a bare number is bytes."""
    t = str(text).strip().upper().removesuffix("B")
    mult = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(t[-1:], 1)
    try:
        value = float(t[:-1] if mult > 1 else t)
    except ValueError:
        raise BagError(f"size {text!r}: expected a number of bytes with an optional K/M/G suffix") from None
    if value < 0:
        raise BagError(f"size {text!r}: must be >= 0")
    return int(value * mult)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "topics",
        nargs="*",
        metavar="TOPIC",
        help="topics to record, full or relative to the launch namespace (default: all)",
    )
    parser.add_argument("-o", "--output", required=True, metavar="FILE.mcap", help="the bag to write")
    parser.add_argument(
        "--graph",
        default=None,
        metavar="FILE",
        help="graph.json or run directory of a launch (default: the newest running launch)",
    )
    parser.add_argument(
        "--compression",
        choices=COMPRESSIONS,
        default="none",
        help="chunk compression (default none: zstd costs a core per ~45 frames/s)",
    )
    parser.add_argument("--chunk-size", default="1M", metavar="SIZE", help="bytes per chunk (default 1M)")
    parser.add_argument(
        "--chunk-age",
        type=float,
        default=1.0,
        metavar="S",
        help="close a chunk this many seconds after its first message (default 1)",
    )
    parser.add_argument(
        "--queue",
        type=int,
        default=8,
        metavar="N",
        help="messages per topic received ahead of the writes; a backlog beyond waits in the publisher's "
        "queue (default 8; 0: unlimited)",
    )
    parser.add_argument(
        "--transport",
        choices=("shm", "zmq"),
        default="shm",
        help="shm (default): frames from publishers on this host through shared memory, only the slot's "
        "name over ZeroMQ; zmq: every byte over the socket (docs/recording.md)",
    )
    split = parser.add_mutually_exclusive_group()
    split.add_argument(
        "--split-size",
        default="0",
        metavar="SIZE",
        help="start FILE_001.mcap, … beyond this size, e.g. 1G (default: one file)",
    )
    split.add_argument(
        "--split-duration",
        type=float,
        default=0.0,
        metavar="S",
        help="start a new file every S seconds (default: one file)",
    )


def main(args: argparse.Namespace) -> int:

    graph_file = find_graph(args.graph)
    graph = load_graph(graph_file)
    endpoints = sorted({n["pub"] for n in graph.get("nodes", {}).values() if n.get("pub")})
    params = {
        "path": os.path.abspath(args.output),
        "topics": list(args.topics),
        "graph": str(graph_file),
        "compression": args.compression,
        "chunk_size": parse_bytes(args.chunk_size),
        "chunk_age_s": args.chunk_age,
        "receive_queue": args.queue,
        "transport": args.transport,
        "split_size": parse_bytes(args.split_size),
        "split_duration_s": args.split_duration,
        "heartbeat_s": 0.0,
    }
    return run_node(
        RECORDER,
        name=f"record-{os.getpid()}",
        namespace=graph.get("namespace", ""),
        params=params,
        connect=endpoints,
    )
