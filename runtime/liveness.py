"""Liveness: which peers of a launch are alive, which came back as a new incarnation, and the little state a
node keeps in the run directory so that a respawned node goes on where the old one stopped.

**Heartbeats.** Every node publishes :class:`~polarstripe.msgs.Heartbeat` on ``heartbeat`` every
``heartbeat_s`` (0.25 s by default) from a thread of its own (``runtime/runner.py``), so a node busy in a long
handler still beats; a process that dies (``kill -9``) stops beating at once. Besides the counters, a beat
carries ``counters["incarnation"]`` (how many times the launcher had respawned the node when it started:
0, 1, 2 …), ``counters["heartbeat_ms"]`` (its period, so a watcher knows the deadline without the graph),
``counters["starting"] = 1`` while its ``setup`` runs (it beats from before setup: alive, not yet ready) and,
in the last beat of an orderly exit, ``counters["exiting"] = 1``.

**The watch.** :class:`Liveness` turns beats into verdicts: a peer heard before is *lost* when it has not
beaten for ``misses`` of its own periods (4 × 0.25 s = 1 s by default; :data:`STARTING_DEADLINE_S` while it
says it is starting: a setup that compiles or plans may hold the interpreter for a while), when its last beat
said it was exiting, or when a beat shows a higher incarnation than the one heard before (it died and came
back between two checks). :meth:`Node.watch <polarstripe.runtime.node.Node.watch>` gives a node one, fed by
its heartbeat subscription; ``wait_for(…, peers=[…])`` then raises :class:`PeerLost`, naming the peer, as soon
as a peer the wait depends on is lost (within a deadline plus one ``wait_for`` slice of 0.05 s).

**Run state.** :class:`RunState` is one small JSON document per node in ``<run_dir>/state/<node>.json``
(``run_dir`` from the launch graph; in memory only without one). The emitter keeps its next scan id there
(ids never repeat across incarnations), the simulator its source pose, the polarizer its calibration, the
planner the medium its plan assumes.
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from polarstripe.errors import PolarstripeError
from polarstripe.msgs import Heartbeat

__all__ = ["DEFAULT_MISSES", "INCARNATION_ENV", "STARTING_DEADLINE_S", "HeartbeatThread", "Liveness", "Peer",
           "PeerLost", "RunState", "Watching", "incarnation"]

INCARNATION_ENV = "POLARSTRIPE_INCARNATION"
"""Set by the launcher for each start of a node: 0 the first time, then its respawn count."""

DEFAULT_MISSES = 4
"""A peer is lost after this many of its heartbeat periods without a beat."""


STARTING_DEADLINE_S = 10.0
"""How long a peer whose last beat said ``starting`` may stay silent before it is lost [s]."""


def incarnation(environ: dict | None = None) -> int:
    """This process's incarnation (``$POLARSTRIPE_INCARNATION``; 0 when started by hand or unreadable)."""
    text = (os.environ if environ is None else environ).get(INCARNATION_ENV, "0")
    try:
        return max(0, int(text))
    except ValueError:
        return 0


class PeerLost(PolarstripeError):
    """A peer a wait depended on is gone: no heartbeat within its deadline, an exit, or a respawn.

    Attributes ``node`` (the peer's name), ``reason`` (what was seen), ``incarnation`` (the last one heard),
    ``respawned`` (True when a newer incarnation is already beating)."""

    def __init__(self, node: str, reason: str, incarnation: int = 0, respawned: bool = False):
        self.node, self.reason, self.incarnation, self.respawned = node, reason, incarnation, respawned
        super().__init__(f"node {node!r} lost: {reason}")


@dataclass
class Peer:
    """What the watch knows of one peer."""

    name: str
    incarnation: int
    pid: int
    period_s: float  # its heartbeat period (0: unknown, the watch's default is used)
    last_s: float  # when it was last heard (the watcher's clock)
    exiting: bool = False  # its last beat said it was stopping
    starting: bool = False  # its last beat said its setup was still running
    lost: str = ""  # why it was declared lost ("" while alive)
    lost_incarnation: int = -1  # the incarnation that was lost (a newer one beating means it came back)


class Liveness:
    """Heartbeat deadlines and incarnations of the peers heard so far (pure logic on the given clock).

    ``heard(hb)`` for each beat, ``check(peers)`` to learn whether any of ``peers`` is lost (a
    :class:`PeerLost`, or None), ``back(name, since)`` whether a peer beats again with an incarnation above
    ``since``."""

    def __init__(self, clock: Callable[[], float], *, misses: int = DEFAULT_MISSES,
                 default_period_s: float = 0.25):
        if misses < 1 or not default_period_s > 0:
            raise ValueError(f"misses must be >= 1 and default_period_s > 0, got {misses}, "
                             f"{default_period_s}")
        self.clock, self.misses, self.default_period_s = clock, misses, default_period_s
        self.peers: dict[str, Peer] = {}

    def deadline_s(self, name: str) -> float:
        """How long ``name`` may stay silent before it is lost [s]."""
        peer = self.peers.get(name)
        period = peer.period_s if peer is not None and peer.period_s > 0 else self.default_period_s
        if peer is not None and peer.starting:
            return max(self.misses * period, STARTING_DEADLINE_S)
        return self.misses * period

    def heard(self, hb: Heartbeat) -> Peer:
        """Note a beat. A higher incarnation than the one heard means the peer was respawned: the old one is
        lost (if it was not already) and the new one is alive."""
        now, c = self.clock(), hb.counters
        inc, period = int(c.get("incarnation", 0)), c.get("heartbeat_ms", 0) / 1000.0
        peer = self.peers.get(hb.node)
        if peer is None or inc > peer.incarnation or (inc == peer.incarnation and hb.pid != peer.pid):
            if peer is not None and not peer.lost:
                peer.lost, peer.lost_incarnation = (
                    f"respawned (incarnation {peer.incarnation} -> {inc}, pid {peer.pid} -> {hb.pid})",
                    peer.incarnation)
            old = peer
            peer = self.peers[hb.node] = Peer(hb.node, inc, hb.pid, period, now)
            if old is not None:  # the new incarnation carries the verdict on the old one until it is taken
                peer.lost, peer.lost_incarnation = old.lost, old.lost_incarnation
        elif inc < peer.incarnation:  # a late beat of an older incarnation
            return peer
        peer.last_s, peer.period_s = now, period or peer.period_s
        peer.starting = bool(c.get("starting"))
        if c.get("exiting"):
            peer.exiting = True
            if not peer.lost:
                peer.lost, peer.lost_incarnation = "exited (its last heartbeat said so)", peer.incarnation
        return peer

    def check(self, names: Iterable[str]) -> PeerLost | None:
        """The first of ``names`` (peers heard at least once) that is lost, as a :class:`PeerLost`; None
        when all are alive. Peers never heard are not judged (start-up waits for them elsewhere)."""
        now = self.clock()
        for name in names:
            peer = self.peers.get(name)
            if peer is None:
                continue
            if not peer.lost:
                silent = now - peer.last_s
                if silent > self.deadline_s(name):
                    peer.lost = f"no heartbeat for {silent:.2f} s (deadline {self.deadline_s(name):g} s)"
                    peer.lost_incarnation = peer.incarnation
            if peer.lost:
                back = peer.incarnation > peer.lost_incarnation
                return PeerLost(name, peer.lost, peer.lost_incarnation, respawned=back)
        return None

    def forgive(self, name: str) -> None:
        """Take note of a loss (after handling it): ``check`` judges the peer afresh from now on."""
        peer = self.peers.get(name)
        if peer is not None and peer.incarnation > peer.lost_incarnation:
            peer.lost, peer.lost_incarnation = "", -1

    def back(self, name: str, since: int) -> bool:
        """Whether ``name`` beats again (not exiting) with an incarnation above ``since``."""
        peer = self.peers.get(name)
        return (peer is not None and peer.incarnation > since and not peer.exiting
                and self.clock() - peer.last_s <= self.deadline_s(name))


class RunState:
    """A node's small JSON state in the run directory, ``<run_dir>/state/<node>.json``: what a respawned
    node needs to go on (written atomically at each :meth:`save`; kept in memory only without a run
    directory, e.g. a node started by hand or in the harness)."""

    def __init__(self, run_dir: str | os.PathLike | None, node: str):
        self.path = Path(run_dir) / "state" / f"{node}.json" if run_dir else None
        self._values: dict[str, Any] = {}
        if self.path is not None and self.path.is_file():
            try:
                loaded = json.loads(self.path.read_text())
                self._values = loaded if isinstance(loaded, dict) else {}
            except (OSError, ValueError):
                self._values = {}

    @classmethod
    def of(cls, graph: dict, node: str) -> RunState:
        """The state of ``node`` in the run directory of launch ``graph`` (``{}``: in memory)."""
        return cls(graph.get("run_dir"), node)

    def get(self, key: str, default: Any = None) -> Any:
        return self._values.get(key, default)

    def __contains__(self, key: str) -> bool:
        return key in self._values

    def save(self, **values: Any) -> None:
        """Merge ``values`` (JSON types) and write the file (temporary file, then rename)."""
        self._values.update(values)
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self._values, indent=1))
        os.replace(tmp, self.path)


class Watching:
    """The part of :class:`~polarstripe.runtime.node.Node` that watches its peers (a mixin: it uses the
    node's subscriptions, bus and clock)."""

    liveness: Liveness | None = None
    _watch_topic: str | None = None
    _beat_period_s: float | None = None

    @property
    def beat_period_s(self) -> float:
        """This node's heartbeat period [s]: ``heartbeat_s``, or longer if ``setup`` says so (a node whose
        compiled kernels hold the GIL for up to a second, e.g. the simulator at ``reference`` fidelity,
        would otherwise miss its deadline while alive). Its beats carry it (``heartbeat_ms``), so watchers
        give it 4 of these periods."""
        return self._beat_period_s if self._beat_period_s is not None else self.params.heartbeat_s

    @beat_period_s.setter
    def beat_period_s(self, value: float) -> None:
        self._beat_period_s = float(value)

    def watch(self, topic: str = "heartbeat", *, misses: int = DEFAULT_MISSES) -> Liveness:
        """Watch the heartbeats on ``topic`` (subscribed here, ``all`` mode, unless it is): each beat the node
        takes (its loop, ``take``, ``wait_for``) feeds :attr:`liveness`; ``wait_for(…, peers=[…])`` raises
        :class:`PeerLost` when one of those peers is lost."""
        if topic not in self._subs:
            self.subscribe(topic, msg_type=Heartbeat, mode="all")
        self.liveness, self._watch_topic = Liveness(self.now, misses=misses), topic
        return self.liveness

    def _feed(self, topic: str, item) -> None:
        if topic == self._watch_topic:
            self.liveness.heard(item)

    def check_peers(self, peers: Iterable[str], topic: str | None = None) -> None:
        """Hand the beats that have arrived to the watch (they are not handed out again; not while waiting
        on the watched ``topic`` itself), then raise :class:`PeerLost` for the first of ``peers`` that is
        lost (e.g. after a fault: did a peer die under it?)."""
        if topic != self._watch_topic:  # every beat that has arrived (the bus hands them one at a time)
            source = self._subs[self._watch_topic].source
            while items := self._bus.take(source, 0.0):
                for item in items:
                    if isinstance(item, Heartbeat):
                        self.liveness.heard(item)
        lost = self.liveness.check(peers)
        if lost is not None:
            raise lost


class HeartbeatThread:
    """Calls ``beat()`` every ``period_s`` from a daemon thread of its own until :meth:`stop`: a node busy
    in a long handler (a render, a plan) still beats, a dead process does not. ``beat`` must be safe to
    call from another thread (the runner's publishers share the PUB socket under a lock)."""

    def __init__(self, period_s: float, beat: Callable[[], Any], *, name: str = "heartbeat"):
        self.period_s, self._beat = period_s, beat
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)

    def start(self) -> HeartbeatThread:
        self._thread.start()
        return self

    def _loop(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self._beat()
            except Exception:  # noqa: BLE001 - a closed socket at exit: the process is ending anyway
                return

    def stop(self, timeout_s: float = 1.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
