"""The recorder node: records topics of a running launch to MCAP (``polarstripe record``, tools/record.py,
runs it by itself; ``polarstripe launch FILE --record run.mcap`` adds it to the launch).

The recorder subscribes to every chosen topic with ``mode="all"`` (no message is skipped; sequence gaps,
i.e. messages lost upstream, are counted per topic and reported at the end and in the bag's ``recording``
metadata). Each message is written as it arrives (log time = receive time, publish time = the header's
``stamp_ns``) without copying its arrays (:class:`~polarstripe.runtime.bag.BagWriter`). Small chunks
closed by size and age, and optional rotation by size or duration, bound what a SIGKILL can lose to the open
chunk; SIGINT/SIGTERM finish the file cleanly. A rotated file is flushed to disk (``fsync``) on a thread, so
the loop never stops receiving for longer than a write.

Receive buffers are reused: each topic's receive queue holds ``receive_queue`` messages (a backlog beyond
waits in the publisher's queue, where a message costs no copy; what overflows that is lost upstream and
counted as a gap), and freed buffers stay in the process (``polarstripe.heap.keep_freed``), so frames
arrive in pages already mapped instead of fresh ones (docs/architecture.md, "Throughput").
"""

from __future__ import annotations

import importlib
import json
import os
import platform
import threading
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Literal

from polarstripe import __version__
from polarstripe.heap import keep_freed
from polarstripe.msgs import REGISTRY, Message
from polarstripe.runtime.bag import BagError, BagWriter
from polarstripe.runtime.graph import load_graph, pid_alive, resolve, shm_offered
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams

KEEP_FREED_BYTES = 256 << 20  # freed receive buffers kept for reuse (the queue and a chunk of frames fit)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def versions() -> dict[str, str]:
    """Versions of polarstripe, Python and the packages that shape a recording."""


    out = {"polarstripe": __version__, "python": platform.python_version(), "platform": platform.platform()}
    for pkg in ("numpy", "msgpack", "pyzmq", "mcap"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "absent"
    return out


def launch_metadata(graph: dict) -> dict[str, str]:
    """The resolved launch: its graph (nodes with resolved params, endpoints, topics), args and file text."""
    meta = {
        "launch": str(graph.get("launch", "")),
        "namespace": str(graph.get("namespace", "")),
        "file": str(graph.get("file", "")),
        "args": json.dumps(graph.get("args", {}), sort_keys=True),
        "graph": json.dumps(graph, sort_keys=True),
    }
    try:
        meta["toml"] = Path(graph["file"]).read_text()
    except (KeyError, OSError, TypeError):
        meta["toml"] = ""
    return meta


def split_path(path: Path, index: int, split: bool) -> Path:
    """``run.mcap`` when not splitting, else ``run_000.mcap``, ``run_001.mcap``, …"""
    return path.with_name(f"{path.stem}_{index:03d}{path.suffix or '.mcap'}") if split else path


def _message_type(graph: dict, tname: str) -> type[Message] | None:
    """The class of wire type ``tname``, importing the graph's node modules if it is not registered yet."""
    if tname not in REGISTRY:

        for node in graph.get("nodes", {}).values():
            try:
                importlib.import_module(str(node.get("module", "")).partition(":")[0])
            except Exception:  # a node module that does not import here just contributes no types
                pass
    return REGISTRY.get(tname)


class Recorder(Node):
    """Records topics of the launch it runs in (or of the graph file ``graph``) to ``path``."""

    class Params(NodeParams):
        path: str = "run.mcap"
        topics: list[str] = []  # full or relative names; empty: every topic of the graph
        graph: str = ""  # graph file; empty: the graph this node was started with
        compression: Literal["none", "zstd", "lz4"] = "none"
        chunk_size: int = 1 << 20  # bytes
        chunk_age_s: float = 1.0  # a chunk older than this goes to disk [s]
        split_size: int = 0  # start a new file beyond this many bytes (0: never)
        split_duration_s: float = 0.0  # start a new file after this many seconds (0: never)
        receive_queue: int = 8  # messages per topic received ahead of writing; more wait upstream (0: no cap)
        transport: Literal["shm", "zmq"] = "shm"  # shm: frames through shared memory where offered

        def validate(self):
            super().validate()
            if self.chunk_size <= 0 or not self.chunk_age_s > 0:
                raise ValueError(
                    f"chunk_size and chunk_age_s must be > 0, got {self.chunk_size}, {self.chunk_age_s}"
                )
            if self.split_size < 0 or self.split_duration_s < 0 or self.receive_queue < 0:
                raise ValueError("split_size, split_duration_s and receive_queue must be >= 0")

    def setup(self):
        p = self.params
        graph = load_graph(p.graph) if p.graph else self.graph
        self.recorded_graph = graph  # the graph whose topics are recorded (its metadata goes in the bag)
        known = graph.get("topics", {})
        wanted = [resolve(t, self.namespace) for t in p.topics] or sorted(known)
        self.types: dict[str, type[Message]] = {}
        for topic in wanted:
            tname = known.get(topic, {}).get("type")
            cls = _message_type(graph, tname) if tname else None
            if cls is None:
                self.log.warning(
                    "not recording %s: %s",
                    topic,
                    f"unknown message type {tname!r}" if tname else "no node of the graph has it",
                )
                continue
            self.types[topic] = cls
            shm = "view" if p.transport == "shm" and shm_offered(graph, topic) else ""
            self.subscribe(topic, lambda m, t=topic: self.write(t, m), msg_type=cls, mode="all",
                           queue=p.receive_queue, shm=shm)
        if not self.types:
            raise BagError(
                f"recorder: nothing to record (topics {wanted or 'none'} of graph "
                f"{p.graph or graph.get('run_dir', '?')})"
            )
        self.counts = dict.fromkeys(self.types, 0)
        self.gaps = dict.fromkeys(self.types, 0)
        self.restarts = dict.fromkeys(self.types, 0)
        self._last: dict[tuple[str, str], int] = {}
        self.files: list[str] = []
        self.bytes = 0
        self.started_ns = time.time_ns()
        self._split = bool(p.split_size or p.split_duration_s)
        self.writer: BagWriter | None = None
        self._syncing: list[threading.Thread] = []  # fsyncs of rotated files
        self._launcher_pid = int(graph.get("pid") or 0) if p.graph else 0  # a standalone recorder follows it
        keep_freed(KEEP_FREED_BYTES)
        self._open()
        self.every(min(0.25, p.chunk_age_s / 2), self._housekeeping)
        self.log.info("recording %d topics to %s", len(self.types), self.writer.path)

    def _open(self) -> None:
        p = self.params
        path = split_path(Path(p.path), len(self.files), self._split)
        self.writer = BagWriter(
            path, compression=p.compression, chunk_size=p.chunk_size, chunk_age_s=p.chunk_age_s,
            on_torn=self._torn,
        ).start()
        self.files.append(str(path))
        self.writer.add_metadata("launch", launch_metadata(self.recorded_graph))
        self.writer.add_metadata("versions", versions())

    def _close(self, *, wait: bool = True) -> None:
        """Finish the file; its ``fsync`` now (``wait``, the last file) or on a thread (a rotation: the loop
        goes on receiving while the kernel writes the finished file out)."""
        w, self.writer = self.writer, None
        if w is not None:
            w.add_metadata("recording", self.report())
            w.finish(fsync=wait)
            if not wait:
                t = threading.Thread(target=_fsync, args=(w.path,), name="recorder-fsync", daemon=True)
                t.start()
                self._syncing.append(t)

    def write(self, topic: str, msg: Message) -> None:
        """Append one received message (called for every message of every recorded topic)."""
        log_ns = time.time_ns()
        key = (topic, getattr(msg, "node", ""))  # log and heartbeat have one publisher per node
        seq, last = msg.header.seq, self._last.get(key)
        if last is not None:
            if seq > last + 1:
                self.gaps[topic] += seq - last - 1
            elif seq <= last:
                self.restarts[topic] += 1
        self._last[key] = seq
        self.bytes += self.writer.add_message(topic, msg, log_time_ns=log_ns)
        self.counts[topic] += 1
        if self.params.split_size and self.writer.size >= self.params.split_size:
            self._rotate()

    def _torn(self, topic: str) -> None:
        """A message whose ring slot was reused before its chunk reached the file: dropped, a gap."""
        self.gaps[topic] += 1
        self.counts[topic] -= 1

    def _gaps(self, topic: str) -> int:
        """Gaps of ``topic``: the counted ones and ring slots overwritten before the first or after the last
        message received (no ``seq`` jump shows those)."""
        return self.gaps[topic] + getattr(self._subs[topic].source, "unseen_overwritten", 0)

    def _drain(self) -> None:
        """Write what has already arrived when the loop stops (a stop must not drop queued messages)."""
        for topic in self.types:  # full names: subscribed as such
            for msg in self.take(topic):
                self.write(topic, msg)

    def _housekeeping(self) -> None:
        self.writer.flush_stale()
        d = self.params.split_duration_s
        if d and self.writer.stats.message_count and time.monotonic() - self.writer.started_at >= d:
            self._rotate()
        if self._launcher_pid and not pid_alive(self._launcher_pid):
            self.stop("the launch ended")

    def _rotate(self) -> None:
        self._close(wait=False)
        self._open()

    def report(self) -> dict[str, str]:
        """What was recorded so far: per topic messages, gaps and publisher restarts; files; bad messages."""
        topics = {
            t: {
                "type": self.types[t].TYPE,
                "messages": self.counts[t],
                "gaps": self._gaps(t),
                "restarts": self.restarts[t],
                "transport": "shm" if getattr(self._subs[t].source, "shm", "") else "zmq",
            }
            for t in self.types
        }
        return {
            "topics": json.dumps(topics, sort_keys=True),
            "gaps": str(sum(self._gaps(t) for t in self.types)),
            "bad": str(self.counts_bad()),
            "file_index": str(len(self.files) - 1),
            "started_ns": str(self.started_ns),
            "stopped_ns": str(time.time_ns()),
        }

    def counts_bad(self) -> int:
        return int(self.counters.get("bad", 0))

    def teardown(self):
        self._drain()
        self._close()
        for t in self._syncing:  # the rotated files are on disk too before the recorder ends
            t.join()
        total, gaps = sum(self.counts.values()), sum(self._gaps(t) for t in self.types)
        for t in self.types:
            if self.counts[t] or self._gaps(t):
                self.log.info("%s: %d messages, %d gaps", t, self.counts[t], self._gaps(t))
        say = self.log.warning if gaps or self.counts_bad() else self.log.info
        files = self.files[0] if len(self.files) == 1 else f"{len(self.files)} files {self.files[0]} …"
        say(
            "recorded %d messages (%.1f MB) to %s; %d gaps, %d bad",
            total,
            self.bytes / 1e6,
            files,
            gaps,
            self.counts_bad(),
        )
