"""The Node base class: name, namespace, typed params, publishers, subscriptions, services, timers, heartbeat,
and a loop that reads top to bottom.

**The contract.** A node is constructed with the bus it runs on, ``Node(name, bus=bus, namespace=…,
params=…)``: a :class:`~polarstripe.runtime.node_bus.NodeBus` that is built first (the real ZeroMQ bus by
:func:`~polarstripe.runtime.runner.run_node`, the mock bus by
:class:`~polarstripe.runtime.testing.NodeHarness`) and never swapped. The node uses only its own public
calls: ``publisher``, ``subscribe``, ``serve``, ``client``, ``every``/``cancel``, ``wait_for``, ``take``
(runtime/subscription_reads.py), ``now()`` (the bus clock: monotonic, virtual in the harness), ``graph`` (the
launch graph), ``resolve``, ``stop``/``stopping``/``stop_reason``.

A node declares its interface as class attributes (the launcher reads them to write the graph), then wires
handlers in :meth:`Node.setup`::

    class Listener(Node):
        class Params(NodeParams):
            shout: bool = False

        SUBSCRIBES = {"chatter": Log}
        SERVES = {"listener/count": (Empty, Ack)}

        def setup(self):
            self.subscribe("chatter", self.on_chatter, mode="all")
            self.serve("listener/count", lambda req: Ack(ok=True, detail=str(self.count)))
            self.every(1.0, self.report)

Or it overrides :meth:`Node.run` and matches typed events (dora-style)::

        def run(self):
            for event in self.events():
                match event:
                    case Received(topic="chatter", msg=msg): ...
                    case Tick(timer="report"): ...

**The loop.** Everything runs in one thread: handlers never race. :meth:`events` fires due timers, then
waits in ``bus.poll`` (which also answers service requests) until the next timer at most. Long work is not
done in one handler — while it runs nothing else is answered — but as a state machine that timers and
messages step (the emitter's scan). A bad message is logged once (rate-limited), counted (``bad``),
dropped, and the node keeps running. SIGINT/SIGTERM end the loop; sockets are closed on the way out.
"""

from __future__ import annotations

import heapq
import logging
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, ClassVar

from polarstripe.msgs import Heartbeat, Message, MessageError
from polarstripe.runtime.client import Client
from polarstripe.runtime.events import Event, NodeError, NodeStopping, Received, Stop, Tick
from polarstripe.runtime.graph import resolve
from polarstripe.runtime.liveness import PeerLost, Watching
from polarstripe.runtime.node_bus import BusPublisher, BusSource, Handler, NodeBus
from polarstripe.runtime.params import NodeParams, build_params
from polarstripe.runtime.subscription_reads import SubscriptionReads

__all__ = ["Event", "Node", "NodeError", "NodeStopping", "PeerLost", "Received", "Stop", "Tick"]

_COUNTERS = ("published", "received", "bad", "gaps", "skipped", "restarts", "requests", "service_errors")


@dataclass
class _Timer:
    name: str
    period_s: float
    callback: Callable[[], Any] | None
    next_s: float


@dataclass
class _Sub:
    topic: str
    full: str
    msg_type: type[Message]
    callback: Callable[[Message], Any] | None
    mode: str
    source: BusSource


class Node(SubscriptionReads, Watching):
    """Base class of every node. See the module docstring; the public API is listed in
    docs/architecture.md."""

    Params: ClassVar[type[NodeParams]] = NodeParams
    PUBLISHES: ClassVar[dict[str, type[Message]]] = {}
    SUBSCRIBES: ClassVar[dict[str, type[Message]]] = {}
    SERVES: ClassVar[dict[str, tuple[type[Message], type[Message]]]] = {}

    def __init__(
        self,
        name: str,
        *,
        bus: NodeBus,
        namespace: str = "",
        params: NodeParams | dict[str, Any] | None = None,
    ):
        """``params``: overrides as a dict (typed and validated here: ``ParamError``), or a built
        ``Params`` instance. ``bus``: the bus this node runs on (required; see the module docstring)."""
        if bus is None:
            raise NodeError(f"node {name!r}: needs a bus (build it first and pass bus=...)")
        self.name, self.namespace = name, namespace
        if isinstance(params, self.Params):
            self.params = params
        else:
            self.params = build_params(self.Params, params or {}, node=name)
        self.log = logging.getLogger(f"polarstripe.node.{name}")
        self.counters: dict[str, int] = dict.fromkeys(_COUNTERS, 0)
        self.exit_code = 0
        self._bus = bus  # the runtime's; node code goes through the public calls
        self._subs: dict[str, _Sub] = {}
        self._pubs: dict[str, _CountingPublisher] = {}
        self._timers: dict[str, _Timer] = {}
        self._services: dict[str, Handler] = {}
        self._clients: dict[tuple, Client] = {}
        self._stop_reason: str | None = None
        self._started = time.monotonic()
        self.ready = False  # set once setup() is done; until then heartbeats say "starting"
        self._bad_logged: dict[str, int] = {}
        self.incarnation = 0  # set by the runner: how many times the launcher had respawned this node

    # ---- what the node may ask of its runtime ------------------------------------------------------------
    def now(self) -> float:
        """The node's clock [s] (monotonic; virtual in the harness): use it for deadlines and durations."""
        return self._bus.now()

    @property
    def graph(self) -> dict:
        """The launch graph this node runs in (``{}`` when started by hand or in the harness)."""
        return self._bus.graph or {}

    def resolve(self, name: str) -> str:
        """The full name of topic or service ``name`` as this node sees it (namespace, ``~/`` private)."""
        return resolve(name, self.namespace, self.name)

    # ---- wiring (call from setup) ------------------------------------------------------------------------
    def setup(self) -> None:
        """Create publishers, subscriptions, services and timers here."""

    def teardown(self) -> None:
        """Called once after the loop ends, before the sockets close."""

    def publisher(self, topic: str, msg_type: type[Message] | None = None) -> _CountingPublisher:
        """A publisher for ``topic`` (declared in ``PUBLISHES``, or give ``msg_type``); ``.publish(msg)``."""
        msg_type = msg_type or self.PUBLISHES.get(topic)
        if msg_type is None:
            raise NodeError(
                f"node {self.name!r}: topic {topic!r} is not in PUBLISHES; declare it or pass msg_type"
            )
        pub = self._pubs.get(topic)
        if pub is None:
            pub = self._pubs[topic] = _CountingPublisher(
                self, self._bus.publisher(self.resolve(topic), msg_type)
            )
        return pub

    def subscribe(
        self,
        topic: str,
        callback: Callable[[Message], Any] | None = None,
        *,
        msg_type: type[Message] | None = None,
        mode: str = "latest",
        queue: int | None = None,
        shm: str = "",
    ) -> None:
        """Receive ``topic`` (declared in ``SUBSCRIBES``, or give ``msg_type``).

        ``callback(msg)`` is called by the default :meth:`run`; a loop-style node gets
        :class:`Received` events instead. ``mode`` is ``"latest"`` (newest only) or ``"all"`` (every message,
        sequence gaps counted). ``queue``: messages received ahead of the loop (default 4 for ``latest``,
        unlimited for ``all``); beyond it a backlog waits in the publisher's queue (its ``hwm``, where a
        message costs no copy) and what overflows that is lost upstream and counted as a gap. ``shm``
        (``"copy"``, ``"view"``): frames through shared memory where the publishers offer it (runtime/bus.py).
        """
        msg_type = msg_type or self.SUBSCRIBES.get(topic)
        if msg_type is None:
            raise NodeError(
                f"node {self.name!r}: topic {topic!r} is not in SUBSCRIBES; declare it or pass msg_type"
            )
        if topic in self._subs:
            raise NodeError(f"node {self.name!r}: already subscribed to {topic!r}")
        full = self.resolve(topic)
        source = self._bus.subscribe(full, msg_type, mode, self.params.max_message_bytes, queue, shm)
        self._subs[topic] = _Sub(topic, full, msg_type, callback, mode, source)

    def serve(self, service: str, handler: Handler) -> None:
        """Answer ``service`` (declared in ``SERVES`` as ``(request type, reply type)``) with ``handler``:
        ``handler(request) -> reply``, or a :class:`~polarstripe.runtime.node_bus.Deferred` to reply later
        from the loop (work the loop steps)."""
        if service not in self.SERVES:
            raise NodeError(f"node {self.name!r}: service {service!r} is not in SERVES")
        req, resp = self.SERVES[service]
        self._services[service] = handler
        self._bus.serve(self.resolve(service), req, resp, handler)

    def client(
        self, service: str, req_type: type[Message], resp_type: type[Message], *, timeout_s: float = 2.0
    ) -> Client:
        """The node's client of ``service`` (served by some node of the launch), made once per service, types
        and timeout: ``.call(request, timeout_s=None, *, retry_s=0.0)``, ``.wait_for_service(timeout_s)``; a
        call fails as soon as the serving node is lost (runtime/client.py)."""
        key = (service, req_type, resp_type, timeout_s)
        made = self._clients.get(key)
        if made is None:
            full = self.resolve(service)
            server = self.graph.get("services", {}).get(full, {}).get("node")
            watch = self._bus.server_watch(self.resolve("heartbeat")) if server else None
            made = self._clients[key] = Client(self._bus.client(full, req_type, resp_type, timeout_s),
                                               server=server, watch=watch, now=self.now,
                                               stopping=lambda: self.stopping)
        return made

    def every(
        self, period_s: float, callback: Callable[[], Any] | None = None, *, name: str | None = None
    ) -> str:
        """Fire every ``period_s`` [s] (fixed rate; missed periods are skipped, not queued). Returns its name,
        which :class:`Tick` events carry (default: the callback's name)."""
        if not period_s > 0:
            raise NodeError(f"node {self.name!r}: timer period must be > 0 s, got {period_s}")
        name = name or getattr(callback, "__name__", None) or f"timer{len(self._timers)}"
        if name in self._timers:
            raise NodeError(f"node {self.name!r}: timer {name!r} exists")
        self._timers[name] = _Timer(name, period_s, callback, self.now() + period_s)
        return name

    def cancel(self, timer: str) -> None:
        self._timers.pop(timer, None)

    # ---- stopping ------------------------------------------------------------------------------------------
    def stop(self, reason: str = "stop() called", exit_code: int | None = None) -> None:
        """End the loop after the current handler returns."""
        self._stop_reason = self._stop_reason or reason
        if exit_code is not None:
            self.exit_code = exit_code

    @property
    def stopping(self) -> bool:
        return self._stop_reason is not None

    @property
    def stop_reason(self) -> str | None:
        """Why the node is stopping (``"SIGINT"``, the text given to :meth:`stop`), None while running."""
        return self._stop_reason

    # ---- the loop ------------------------------------------------------------------------------------------
    def events(self) -> Iterator[Event]:
        """Typed events in arrival order until the node stops; ends with one :class:`Stop`.

        Service requests are answered inside (by their handlers, in ``bus.poll``), bad messages are logged
        and counted here.
        """
        while self._stop_reason is None:
            yield from self._due_timers()
            if self._stop_reason is not None:
                break
            yield from self._arrived()
        yield Stop(self._stop_reason)

    def _due_timers(self) -> Iterator[Tick]:
        now = self.now()
        due = [t for t in self._timers.values() if t.next_s <= now]
        for t in heapq.nsmallest(len(due), due, key=lambda t: t.next_s):
            t.next_s += t.period_s
            if t.next_s <= now:  # fell behind: skip the missed periods
                t.next_s = now + t.period_s
            if t.name.startswith("_"):  # the runtime's own timers (heartbeat) are not the node's events
                t.callback()
            else:
                yield Tick(t.name, int(now * 1e9))
            if self._stop_reason is not None:
                return

    def _arrived(self) -> Iterator[Received]:
        """Wait until the next timer (0.1 s at most) for messages; yield them in publication order."""
        now = self.now()
        next_due = min((t.next_s for t in self._timers.values()), default=now + 0.1)
        subs = {id(s.source): s for s in self._subs.values()}
        ready = self._bus.poll([s.source for s in subs.values()], min(max(0.0, next_due - self.now()), 0.1))
        batch = []
        for source, items in ready:
            sub = subs[id(source)]
            for item in items:
                if isinstance(item, MessageError):
                    self._bad(sub.topic, item)
                else:
                    self._feed(sub.topic, item)
                    batch.append((item.header.stamp_ns, sub.topic, item))
        if len(ready) > 1:  # several topics at once: deliver in publication order, not topic by topic
            batch.sort(key=lambda b: b[0])
        for _, topic, item in batch:
            yield Received(topic, item)
            if self._stop_reason is not None:
                return

    def run(self) -> None:
        """The default loop: call the callbacks given to :meth:`subscribe` and :meth:`every`."""
        for event in self.events():
            self.dispatch(event)

    def dispatch(self, event: Event) -> None:
        match event:
            case Received(topic=topic, msg=msg):
                cb = self._subs[topic].callback
                if cb is not None:
                    cb(msg)
            case Tick(timer=name):
                t = self._timers.get(name)
                if t is not None and t.callback is not None:
                    t.callback()
            case Stop():
                pass

    # ---- internals -----------------------------------------------------------------------------------------
    def _bad(self, topic: str, exc: MessageError) -> None:
        self.counters["bad"] += 1
        n = self._bad_logged[topic] = self._bad_logged.get(topic, 0) + 1
        if n <= 5 or n % 100 == 0:
            more = f" ({n} bad on this topic so far)" if n > 1 else ""
            self.log.warning("dropped bad message: %s%s", exc, more)

    def heartbeat(self, *, exiting: bool = False) -> Heartbeat:
        """The :class:`Heartbeat` as things stand: the node's counters with its subscriptions' and
        services' statistics, its ``incarnation`` and ``heartbeat_ms`` (and ``exiting`` = 1 in the last beat
        of an orderly exit): runtime/liveness.py. Called from the runner's heartbeat thread."""
        c = dict(self.counters)
        subs = list(self._subs.values())  # a copy: the loop's thread may subscribe meanwhile
        for key in ("received", "gaps", "skipped", "restarts"):
            c[key] = sum(getattr(s.source.stats, key, 0) for s in subs)
        requests, errors, bad = self._bus.service_stats()
        c["bad"] = self.counters["bad"] + bad
        c["requests"], c["service_errors"] = requests, errors
        c["incarnation"], c["heartbeat_ms"] = self.incarnation, round(self.beat_period_s * 1000)
        if not self.ready:
            c["starting"] = 1
        if exiting:
            c["exiting"] = 1
        return Heartbeat(
            node=self.name, pid=os.getpid(), uptime_s=time.monotonic() - self._started, counters=c
        )


class _CountingPublisher:
    """Wraps a bus publisher to count what the node publishes."""

    def __init__(self, node: Node, pub: BusPublisher):
        self._node, self._pub = node, pub
        self.topic, self.msg_type = pub.topic, pub.msg_type

    def publish(self, msg: Message, *, stamp_ns: int | None = None) -> int:
        seq = self._pub.publish(msg, stamp_ns=stamp_ns)
        self._node.counters["published"] += 1
        return seq
