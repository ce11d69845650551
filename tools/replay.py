"""``polarstripe replay FILE [--rate R] [--loop] [--topics …] [--start S] [--graph FILE | --pub ENDPOINT]``:
publish a recording on its original topics with the :class:`~polarstripe.nodes.replayer.Replayer` node, run by
itself; it writes a graph file like the launcher's, so ``topic``, ``record`` and ``view`` find it.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import time
from pathlib import Path

from polarstripe.runtime.bag_reader import BagReader
from polarstripe.runtime.graph import runs_dir, write_graph
from polarstripe.runtime.launch_file import sock_dir
from polarstripe.runtime.runner import run_node

HELP = "publish a recording on its original topics"
REPLAYER = "polarstripe.nodes.replayer:Replayer"


# ---- the command -------------------------------------------------------------------------------------------
def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE", help="the bag (MCAP) to replay")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed (default 1: as recorded)")
    parser.add_argument("--loop", action="store_true", help="start again at the end")
    parser.add_argument("--topics", nargs="+", default=[], metavar="TOPIC", help="only these topics")
    parser.add_argument("--start", type=float, default=0.0, metavar="S", help="skip the first S seconds")
    parser.add_argument(
        "--delay",
        type=float,
        default=1.0,
        metavar="S",
        help="wait before the first message so subscribers can connect (default 1)",
    )
    parser.add_argument("--name", default="replay", help="node name (default replay)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--graph",
        default=None,
        metavar="FILE",
        help="write the replay's graph file here (default: a new run directory, found by "
        "'topic', 'record' and 'view' as the newest running launch)",
    )
    where.add_argument(
        "--pub",
        default=None,
        metavar="ENDPOINT",
        help="bind the publisher here, e.g. tcp://0.0.0.0:5600 (default: ipc in the run directory)",
    )


def replay_graph(bag: BagReader, name: str, topics: list[str], run_dir: Path, pub: str) -> dict:
    """A graph file (the launcher's layout) with one node, the replayer, publishing ``topics``."""
    ns = bag.metadata.get("launch", {}).get("namespace", "")
    publishes = {t: bag.topics[t].type for t in topics}
    return {
        "launch": f"replay:{bag.path.name}",
        "file": str(bag.path),
        "namespace": ns,
        "run_dir": str(run_dir),
        "pid": os.getpid(),
        "started_ns": time.time_ns(),
        "state": "running",
        "args": {},
        "nodes": {
            name: {
                "module": REPLAYER,
                "pub": pub,
                "srv": "",
                "publishes": publishes,
                "subscribes": {},
                "serves": {},
                "params": {},
                "required": True,
                "pid": os.getpid(),
            }
        },
        "topics": {t: {"type": typ, "publishers": [name], "subscribers": []} for t, typ in publishes.items()},
        "services": {},
    }


def main(args: argparse.Namespace) -> int:

    with BagReader(args.file) as bag:  # check the file (and the topics) before binding anything
        topics = bag.resolve_topics(args.topics) or list(bag.topics)
        if args.graph:
            graph_file = Path(args.graph)
            run_dir = graph_file.parent
        else:
            run_dir = runs_dir() / f"replay-{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}"
            graph_file = run_dir / "graph.json"
        run_dir.mkdir(parents=True, exist_ok=True)
        pub = args.pub or f"ipc://{sock_dir(run_dir) / (args.name + '.pub')}"
        graph = replay_graph(bag, args.name, topics, run_dir, pub)
    write_graph(graph_file, graph)
    print(f"replay: graph {graph_file}, publishing {len(topics)} topics at {pub}", flush=True)
    params = {
        "path": os.path.abspath(args.file),
        "rate": args.rate,
        "loop": args.loop,
        "topics": topics,
        "start_s": args.start,
        "delay_s": args.delay,
        "progress": True,
        "linger_s": 0.2,
    }
    try:
        return run_node(
            REPLAYER,
            name=args.name,
            graph_file=str(graph_file),
            params=params,
            srv=f"ipc://{sock_dir(run_dir) / (args.name + '.srv')}",
        )
    finally:
        graph["state"] = "stopped"
        write_graph(graph_file, graph)
        with contextlib.suppress(OSError):  # the socket folder, once the node has closed its sockets
            sock_dir(run_dir).rmdir()
