"""The Node base class: name, namespace, typed params, publishers, subscriptions, services, timers, heartbeat,
logging to stderr and to the ``log`` topic, and a loop that reads top to bottom.

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

Everything runs in one thread: handlers never race. A bad message is logged once (rate-limited), counted
(``bad``), dropped, and the node keeps running. SIGINT/SIGTERM end the loop; sockets are closed on the
way out.
"""

from __future__ import annotations

import heapq
import logging
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, ClassVar

from polarstripe.errors import PolarstripeError
from polarstripe.msgs import Heartbeat, Log, Message, MessageError
from polarstripe.runtime.bus import BusTimeout
from polarstripe.runtime.graph import resolve
from polarstripe.runtime.params import NodeParams, build_params


class NodeError(PolarstripeError):
    """A node used wrongly (undeclared topic, duplicate timer); the text names the node and what."""


class NodeStopping(PolarstripeError):
    """A blocking call (:meth:`Node.wait_for`) gave up because the node was told to stop (SIGINT, SIGTERM,
    :meth:`Node.stop`). Not a ``TimeoutError``: a caller can tell "stopping" from "nothing came in time".

    Let it propagate to end the node: escaping a callback or :meth:`Node.run`, it ends the node normally
    (``teardown`` runs, the exit status stays :attr:`Node.exit_code`); catch it only to publish a fault or
    clean up. Attributes ``node``, ``topic`` and ``reason`` (the stop reason).
    """

    def __init__(self, node: str, topic: str, reason: str):
        self.node, self.topic, self.reason = node, topic, reason
        super().__init__(f"node {node!r}: stopped waiting for {topic!r}: the node is stopping ({reason})")


# ---- events -----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Received:
    """A message arrived on ``topic`` (the name as the node declared it, e.g. ``"camera/frame"``)."""

    topic: str
    msg: Message


@dataclass(frozen=True)
class Tick:
    """Timer ``timer`` fired; ``now_ns`` is the monotonic clock [ns]."""

    timer: str
    now_ns: int


@dataclass(frozen=True)
class Stop:
    """The loop is ending (``reason``: ``"SIGINT"``, ``"SIGTERM"``, or the text given to
    :meth:`Node.stop`)."""

    reason: str


Event = Received | Tick | Stop

STOP_CHECK_S = 0.05
"""How often a blocking :meth:`Node.wait_for` looks whether the node was told to stop [s]."""


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
    source: Any  # a bus Subscriber (or the harness' stand-in)


class Node:
    """Base class of every node. See the module docstring; the public API is listed in
    docs/architecture.md."""

    Params: ClassVar[type[NodeParams]] = NodeParams
    PUBLISHES: ClassVar[dict[str, type[Message]]] = {}
    SUBSCRIBES: ClassVar[dict[str, type[Message]]] = {}
    SERVES: ClassVar[dict[str, tuple[type[Message], type[Message]]]] = {}

    def __init__(
        self, name: str, *, namespace: str = "", params: dict[str, Any] | None = None, bus: Any = None
    ):
        self.name, self.namespace = name, namespace
        self.params = build_params(self.Params, params or {}, node=name)
        self._resolve = lambda n: resolve(n, namespace, name)
        self.log = logging.getLogger(f"polarstripe.node.{name}")
        self.counters: dict[str, int] = {
            "published": 0,
            "received": 0,
            "bad": 0,
            "gaps": 0,
            "skipped": 0,
            "restarts": 0,
            "requests": 0,
            "service_errors": 0,
        }
        self.exit_code = 0
        self._bus = bus
        self._subs: dict[str, _Sub] = {}
        self._pubs: dict[str, Any] = {}
        self._timers: dict[str, _Timer] = {}
        self._services: dict[str, Callable] = {}
        self._stop_reason: str | None = None
        self._started = time.monotonic()
        self._bad_logged: dict[str, int] = {}

    # ---- wiring (call from setup) ------------------------------------------------------------------------
    def setup(self) -> None:
        """Create publishers, subscriptions, services and timers here."""

    def teardown(self) -> None:
        """Called once after the loop ends, before the sockets close."""

    def publisher(self, topic: str, msg_type: type[Message] | None = None):
        """A publisher for ``topic`` (declared in ``PUBLISHES``, or give ``msg_type``); ``.publish(msg)``."""
        msg_type = msg_type or self.PUBLISHES.get(topic)
        if msg_type is None:
            raise NodeError(
                f"node {self.name!r}: topic {topic!r} is not in PUBLISHES; declare it or pass msg_type"
            )
        pub = self._pubs.get(topic)
        if pub is None:
            pub = self._pubs[topic] = _CountingPublisher(
                self, self._bus.publisher(self._resolve(topic), msg_type)
            )
        return pub

    def subscribe(
        self,
        topic: str,
        callback: Callable[[Message], Any] | None = None,
        *,
        msg_type: type[Message] | None = None,
        mode: str = "latest",
    ) -> None:
        """Receive ``topic`` (declared in ``SUBSCRIBES``, or give ``msg_type``).

        ``callback(msg)`` is called by the default :meth:`run`; a loop-style node gets
        :class:`Received` events instead. ``mode`` is ``"latest"`` (newest only) or ``"all"`` (every message,
        sequence gaps counted).
        """
        msg_type = msg_type or self.SUBSCRIBES.get(topic)
        if msg_type is None:
            raise NodeError(
                f"node {self.name!r}: topic {topic!r} is not in SUBSCRIBES; declare it or pass msg_type"
            )
        if topic in self._subs:
            raise NodeError(f"node {self.name!r}: already subscribed to {topic!r}")
        full = self._resolve(topic)
        self._subs[topic] = _Sub(
            topic,
            full,
            msg_type,
            callback,
            mode,
            self._bus.subscribe(full, msg_type, mode, self.params.max_message_bytes),
        )

    def serve(self, service: str, handler: Callable[[Message], Message]) -> None:
        """Answer ``service`` (declared in ``SERVES`` as ``(request type, reply type)``) with ``handler``."""
        if service not in self.SERVES:
            raise NodeError(f"node {self.name!r}: service {service!r} is not in SERVES")
        req, resp = self.SERVES[service]
        self._services[service] = handler
        self._bus.serve(self._resolve(service), req, resp, handler)

    def client(
        self, service: str, req_type: type[Message], resp_type: type[Message], *, timeout_s: float = 2.0
    ):
        """A client of ``service`` (served by some node of the launch): ``.call(request, timeout_s=None)``."""
        return self._bus.client(self._resolve(service), req_type, resp_type, timeout_s)

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
        self._timers[name] = _Timer(name, period_s, callback, self._bus.now() + period_s)
        return name

    def cancel(self, timer: str) -> None:
        self._timers.pop(timer, None)

    def wait_for(self, topic: str, match: Callable[[Message], bool] = lambda m: True, timeout_s: float = 1.0):
        """Block until a message on subscribed ``topic`` satisfies ``match``; non-matching messages before it
        are dropped, those after it stay queued for the next call or the loop.

        Raises :class:`~polarstripe.runtime.bus.BusTimeout` (a ``TimeoutError``) naming the topic
        after ``timeout_s``, or :class:`NodeStopping` within ~``STOP_CHECK_S`` of the node being told to
        stop (SIGINT, SIGTERM, :meth:`stop`; also at once if it already was).
        """
        sub = self._subs.get(topic)
        if sub is None:
            raise NodeError(f"node {self.name!r}: wait_for({topic!r}) needs a subscription first")
        bus = self._bus
        deadline = bus.now() + timeout_s
        while True:
            if self._stop_reason is not None:
                raise NodeStopping(self.name, sub.full, self._stop_reason)
            # short slices: a signal does not cut a zmq poll short (pyzmq resumes it after the handler)
            for item in bus.take(sub.source, min(max(0.0, deadline - bus.now()), STOP_CHECK_S)):
                if isinstance(item, MessageError):
                    self._bad(topic, item)
                elif match(item):
                    return item
            if bus.now() >= deadline:

                raise BusTimeout(
                    f"node {self.name!r}: no matching message on {sub.full!r} within {timeout_s} s"
                )

    def stop(self, reason: str = "stop() called", exit_code: int | None = None) -> None:
        """End the loop after the current handler returns."""
        self._stop_reason = self._stop_reason or reason
        if exit_code is not None:
            self.exit_code = exit_code

    @property
    def stopping(self) -> bool:
        return self._stop_reason is not None

    # ---- the loop ------------------------------------------------------------------------------------------
    def events(self) -> Iterator[Event]:
        """Typed events in arrival order until the node stops; ends with one :class:`Stop`.

        Service requests are answered inside (by their handlers), bad messages are logged and counted here.
        """
        bus = self._bus
        while self._stop_reason is None:
            now = bus.now()
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
                    break
            if self._stop_reason is not None:
                break
            next_due = min((t.next_s for t in self._timers.values()), default=now + 0.1)
            ready = bus.poll(list(self._subs.values()), min(max(0.0, next_due - bus.now()), 0.1))
            batch = []
            for sub, items in ready:
                for item in items:
                    if isinstance(item, MessageError):
                        self._bad(sub.topic, item)
                    else:
                        batch.append((item.header.stamp_ns, sub.topic, item))
            if len(ready) > 1:  # several topics at once: deliver in publication order, not topic by topic
                batch.sort(key=lambda b: b[0])
            for _, topic, item in batch:
                yield Received(topic, item)
                if self._stop_reason is not None:
                    break
        yield Stop(self._stop_reason)

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

    def heartbeat(self) -> Heartbeat:
        c = dict(self.counters)
        for key in ("received", "gaps", "skipped", "restarts"):
            c[key] = sum(getattr(s.source.stats, key, 0) for s in self._subs.values())
        c["bad"] = self.counters["bad"] + self._bus.server_bad()
        return Heartbeat(
            node=self.name, pid=os.getpid(), uptime_s=time.monotonic() - self._started, counters=c
        )


class _CountingPublisher:
    """Wraps a bus publisher to count what the node publishes."""

    def __init__(self, node: Node, pub: Any):
        self._node, self._pub = node, pub
        self.topic, self.msg_type = pub.topic, pub.msg_type

    def publish(self, msg: Message, *, stamp_ns: int | None = None) -> int:
        seq = self._pub.publish(msg, stamp_ns=stamp_ns)
        self._node.counters["published"] += 1
        return seq


class BusLogHandler(logging.Handler):
    """Publishes log records as :class:`~polarstripe.msgs.Log` on the namespace's ``log`` topic."""

    def __init__(self, node: Node):
        super().__init__()
        self._node = node
        self._pub = None
        self._busy = False

    def emit(self, record: logging.LogRecord) -> None:
        if self._busy:
            return
        self._busy = True
        try:
            if self._pub is None:
                self._pub = self._node._bus.publisher(self._node._resolve("log"), Log)
            level = (
                record.levelname if record.levelname in ("DEBUG", "INFO", "WARNING", "ERROR") else "CRITICAL"
            )
            self._pub.publish(Log(level=level, node=self._node.name, text=record.getMessage()))
        except Exception:  # logging must never take the node down
            pass
        finally:
            self._busy = False


def install_logging(node: Node, *, to_bus: bool = True) -> None:
    """stderr lines ``time LEVEL node: text`` and, if ``to_bus``, the ``log`` topic."""
    log = node.log
    log.setLevel(node.params.log_level)
    log.propagate = False
    for h in list(log.handlers):
        log.removeHandler(h)
    err = logging.StreamHandler(sys.stderr)
    err.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(nodename)s: %(message)s"))
    err.addFilter(lambda r: setattr(r, "nodename", node.name) or True)
    log.addHandler(err)
    if to_bus:
        log.addHandler(BusLogHandler(node))


def install_signals(node: Node) -> None:
    """SIGINT and SIGTERM stop the node's loop (the second SIGINT raises KeyboardInterrupt)."""

    def on_signal(signum, frame):
        name = signal.Signals(signum).name
        if node.stopping and signum == signal.SIGINT:
            raise KeyboardInterrupt
        node.stop(name)

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
