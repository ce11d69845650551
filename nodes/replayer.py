"""The replayer node: publishes a recording on its original topics, paced by log time (``polarstripe replay``,
tools/replay.py, runs it by itself).

Each message is decoded and validated (:meth:`BagReader.messages`) and published with its original header
stamp (``stamp_ns``); sequence numbers are the replayer's own, from 0. How subscribers find the replayer:

* in a launch file, as a node (``module = "polarstripe.nodes.replayer:Replayer"``): the launcher
  assigns its endpoint and the other nodes connect to it (``launch/replay.toml``);
* by hand, ``polarstripe replay`` writes a graph file like the launcher's (a run directory under
  ``$POLARSTRIPE_RUNS``, or ``--graph FILE``) listing the replayer and the topics it publishes, so ``topic``,
  ``record`` and ``view`` find it as the newest running launch; ``--pub`` chooses the endpoint.

ZeroMQ drops what is published before a subscriber has connected, so the replayer waits ``delay_s`` before the
first message; with ``wait_for``, it waits ``delay_s`` after the last named node is ready (a heartbeat that no
longer says ``starting``): a node's subscriptions finish connecting in the background after its setup, and
under load that can take longer than the beat that says it is ready.
"""

from __future__ import annotations

from pathlib import Path

from polarstripe.msgs import CALIBRATION_SCAN_ID, Composite, Heartbeat, ScanEvent
from polarstripe.runtime.bag import BagError
from polarstripe.runtime.bag_reader import BagReader
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams
from tqdm import tqdm


class Replayer(Node):
    """Publishes the messages of bag ``path`` on their recorded topics, ``rate`` times as fast as recorded."""

    class Params(NodeParams):
        path: str = ""
        rate: float = 1.0  # playback speed (2.0: twice as fast)
        loop: bool = False
        topics: list[str] = []  # full or relative names; empty: every topic of the bag
        start_s: float = 0.0  # skip this much of the bag's beginning [s]
        delay_s: float = 1.0  # wait before the first message, for subscribers to connect [s]
        wait_for: list[str] = []  # also wait until each of these nodes is ready, then delay_s more
        linger_s: float = 1.0  # after the last message, stay this long before stopping [s]
        until_composed: bool = False  # stop once every replayed scan's composite is out (linger_s at most)
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
        self._uncomposed: set[int] = set()  # scans replayed to their end whose composite has not come
        if p.until_composed:
            self.subscribe("compositor/composite", self._on_composite, msg_type=Composite, mode="all")
        self._ready_at = self.now() + p.delay_s  # the node's clock: monotonic [s], virtual in the harness
        self._t0: float | None = None
        self._done_at: float | None = None
        self._iter = self._next = None
        self._bar = None
        self.every(0.002, self._pump, name="pump")

    def _on_heartbeat(self, hb: Heartbeat) -> None:
        if not hb.counters.get("starting") and hb.node not in self._seen:  # ready: its setup is done
            self._seen.add(hb.node)
            self._ready_at = max(self._ready_at, self.now() + self.params.delay_s)

    def _on_composite(self, c: Composite) -> None:
        self._uncomposed.discard(c.scan_id)

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
            waited = now - self._done_at
            if self.params.exit_when_done and (waited >= self.params.linger_s or (
                    self.params.until_composed and not self._uncomposed)):
                if self._uncomposed:
                    self.log.warning("no composite of scan(s) %s after %.1f s", sorted(self._uncomposed),
                                     waited)
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
            if isinstance(msg, ScanEvent) and msg.event == "done" and msg.scan_id < CALIBRATION_SCAN_ID:
                self._uncomposed.add(msg.scan_id)
            self._next = None
            self.sent += 1
            if self._bar is not None:
                self._bar.update()

    def teardown(self):
        if self._bar is not None:
            self._bar.close()
        self.bag.close()
