"""``polarstripe replay FILE [--rate R] [--loop] [--topics …] [--start S] [--graph FILE | --pub ENDPOINT]``:
publish a recording on its original topics, paced by log time; and the :class:`Replayer` node that does it.

Each message is decoded and validated (:meth:`BagReader.messages`) and published with its original header
stamp (``stamp_ns``); sequence numbers are the replayer's own, from 0. How subscribers find the replayer:

* in a launch file, as a node (``module = "polarstripe.tools.replay:Replayer"``): the launcher
  assigns its endpoint and the other nodes connect to it (``launch/replay.toml``);
* by hand, ``polarstripe replay`` writes a graph file like the launcher's (a run directory under
  ``$POLARSTRIPE_RUNS``, or ``--graph FILE``) listing the replayer and the topics it publishes, so ``topic``,
  ``record`` and ``view`` find it as the newest running launch; ``--pub`` chooses the endpoint.

ZeroMQ drops what is published before a subscriber has connected, so the replayer waits ``delay_s`` (and,
with ``wait_for``, for a heartbeat of each named node) before the first message.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from polarstripe.msgs import Heartbeat
from polarstripe.runtime.graph import runs_dir, write_graph
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams
from polarstripe.runtime.runner import run_node
from polarstripe.tools.bag import BagError
from polarstripe.tools.bag_reader import BagReader
from tqdm import tqdm

HELP = "publish a recording on its original topics"
REPLAYER = "polarstripe.tools.replay:Replayer"


class Replayer(Node):
    """Publishes the messages of bag ``path`` on their recorded topics, ``rate`` times as fast as recorded."""

    class Params(NodeParams):
        path: str = ""
        rate: float = 1.0  # playback speed (2.0: twice as fast)
        loop: bool = False
        topics: list[str] = []  # full or relative names; empty: every topic of the bag
        start_s: float = 0.0  # skip this much of the bag's beginning [s]
        delay_s: float = 1.0  # wait before the first message, for subscribers to connect [s]
        wait_for: list[str] = []  # also wait for a heartbeat of each of these nodes
        linger_s: float = 1.0  # after the last message, stay this long before stopping [s]
        exit_when_done: bool = True
        progress: bool = False  # a tqdm progress bar on stderr

        def validate(self):
            super().validate()
            if not self.path:
                raise ValueError("path (the bag to replay) is required")
            if not self.rate > 0:
                raise ValueError(f"rate must be > 0, got {self.rate}")
            if self.start_s < 0 or self.delay_s < 0 or self.linger_s < 0:
                raise ValueError("start_s, delay_s and linger_s must be >= 0")

    def setup(self):
        p = self.params
        self.bag = BagReader(p.path)
        chosen = self.bag.resolve_topics(p.topics, self.namespace) or list(self.bag.topics)
        self.topics = chosen
        self.pubs = {}
        for t in chosen:
            cls = self.bag.types[t]
            if cls is None:
                raise BagError(
                    f"bag {p.path}: topic {t!r}: message type {self.bag.topics[t].type!r} is not known "
                    "to this build"
                )
            self.pubs[t] = self.publisher(t, cls)
        self.total = sum(self.bag.topics[t].count for t in chosen)
        self.sent = self.loops = 0
        self._seen: set[str] = set()
        if p.wait_for:
            self.subscribe("heartbeat", self._on_heartbeat, msg_type=Heartbeat, mode="all")
        self._ready_at = self.now() + p.delay_s  # the node's clock: monotonic [s], virtual in the harness
        self._t0: float | None = None
        self._done_at: float | None = None
        self._iter = self._next = None
        self._bar = None
        self.every(0.002, self._pump, name="pump")

    def _on_heartbeat(self, hb: Heartbeat) -> None:
        self._seen.add(hb.node)

    def _begin(self) -> None:
        start_ns = self.bag.start_ns + int(self.params.start_s * 1e9)
        self._iter = self.bag.messages(self.topics, start_ns=start_ns)
        self._next = next(self._iter, None)  # the first read may take a while: start the clock after it
        self._t0, self._b0 = self.now(), start_ns
        if self.params.progress:

            if self._bar is None:
                self._bar = tqdm(total=self.total, unit="msg", desc=Path(self.params.path).name)
            else:
                self._bar.reset()

    def _pump(self) -> None:
        now = self.now()
        if self._done_at is not None:
            if self.params.exit_when_done and now - self._done_at >= self.params.linger_s:
                self.stop(f"replayed {self.sent} messages")
            return
        if self._t0 is None:
            if now < self._ready_at or not set(self.params.wait_for) <= self._seen:
                return
            self._begin()
            now = self.now()
            self.log.info(
                "replaying %d messages of %s at rate %g", self.total, self.params.path, self.params.rate
            )
        rate = self.params.rate
        while True:
            if self._next is None:
                self._next = next(self._iter, None)
                if self._next is None:
                    self.loops += 1
                    if self.params.loop and self.total:
                        self._begin()
                        now = self.now()
                        continue
                    self._done_at = now
                    self.log.info("replay done: %d messages", self.sent)
                    return
            topic, log_ns, msg = self._next
            if self._t0 + (log_ns - self._b0) / 1e9 / rate > now:
                return
            self.pubs[topic].publish(msg)
            self._next = None
            self.sent += 1
            if self._bar is not None:
                self._bar.update()

    def teardown(self):
        if self._bar is not None:
            self._bar.close()
        self.bag.close()


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
        pub = args.pub or f"ipc://{run_dir / (args.name + '.pub')}"
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
            srv=f"ipc://{run_dir / (args.name + '.srv')}",
        )
    finally:
        graph["state"] = "stopped"
        write_graph(graph_file, graph)
