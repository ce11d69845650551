"""Unit-test a node without processes or sockets (like dora's ``MockNode``).

::

    from polarstripe.runtime.testing import NodeHarness

    def test_talker_counts():
        h = NodeHarness(Talker, params={"rate_hz": 10})
        h.advance(0.35)                              # virtual time: fires the 0.1 s timer 3 times
        assert [m.text for m in h.published("chatter")] == ["hello 0", "hello 1", "hello 2"]
        assert h.call("talker/reset", Empty()).ok

Every message crosses the real codec (encode then decode), so a field of the wrong type fails here as it
would on the wire. Logs are kept in :attr:`NodeHarness.logs` as ``(level, text)``.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

from polarstripe.msgs import Message, MessageError, decode, encode
from polarstripe.runtime.bus import ServiceError, ServiceTimeout, SubscriberStats
from polarstripe.runtime.node import Event, Node, NodeStopping, Received, Stop, Tick


def roundtrip(msg: Message, topic: str = "") -> Message:
    """``msg`` after the wire: encoded and decoded (arrays become read-only views)."""
    frames = [bytes(f) if isinstance(f, bytes) else f.tobytes() for f in encode(msg, topic=topic)]
    return decode(frames, topic=topic, expect=type(msg))


class _Pub:
    def __init__(self, bus: MockBus, topic: str, msg_type: type[Message]):
        self.bus, self.topic, self.msg_type, self.seq = bus, topic, msg_type, 0

    def publish(self, msg: Message, *, stamp_ns: int | None = None) -> int:
        if type(msg) is not self.msg_type:
            raise MessageError(
                self.topic, "type", f"expected {self.msg_type.TYPE!r}, got {type(msg).__name__}"
            )
        frames = [
            f if isinstance(f, bytes) else f.tobytes()
            for f in encode(msg, topic=self.topic, seq=self.seq, stamp_ns=stamp_ns)
        ]
        self.bus.sent.setdefault(self.topic, []).append(
            decode(frames, topic=self.topic, expect=self.msg_type)
        )
        self.seq += 1
        return self.seq - 1


class _Source:
    def __init__(self, topic: str, msg_type: type[Message], mode: str):
        self.topic, self.msg_type, self.mode = topic, msg_type, mode
        self.stats = SubscriberStats()
        self.queue: deque = deque()


class _Client:
    def __init__(self, bus: MockBus, service: str, req: type[Message], resp: type[Message], timeout_s: float):
        self.bus, self.name, self.req_type, self.resp_type, self.timeout_s = (
            bus,
            service,
            req,
            resp,
            timeout_s,
        )
        self.requests: list[Message] = []

    def call(self, request: Message, timeout_s: float | None = None) -> Message:
        request = roundtrip(request, self.name)
        self.requests.append(request)
        responder = self.bus.responders.get(self.name)
        if responder is None:
            self.bus.clock += self.timeout_s if timeout_s is None else timeout_s
            raise ServiceTimeout(
                f"service {self.name!r} at <harness>: no reply (no responder set with on_call)"
            )
        try:
            reply = responder(request)
        except Exception as exc:
            raise ServiceError(f"service {self.name!r} at <harness>: {type(exc).__name__}: {exc}") from None
        return roundtrip(reply, self.name)

    def close(self):
        pass


class MockBus:
    """The harness's stand-in for :class:`~polarstripe.runtime.runner.ZmqNodeBus` (virtual clock)."""

    def __init__(self):
        self.clock = 0.0
        self.sent: dict[str, list[Message]] = {}
        self.sources: dict[str, _Source] = {}
        self.handlers: dict[str, tuple[type[Message], type[Message], Callable]] = {}
        self.responders: dict[str, Callable[[Message], Message]] = {}
        self.clients: dict[str, _Client] = {}

    def now(self) -> float:
        return self.clock

    def publisher(self, topic, msg_type):
        return _Pub(self, topic, msg_type)

    def subscribe(self, topic, msg_type, mode, max_bytes):
        src = self.sources[topic] = _Source(topic, msg_type, mode)
        return src

    def serve(self, service, req, resp, handler):
        self.handlers[service] = (req, resp, handler)

    def client(self, service, req, resp, timeout_s):
        c = self.clients[service] = _Client(self, service, req, resp, timeout_s)
        return c

    def take(self, source: _Source, timeout_s: float) -> list:
        if source.queue:
            return [source.queue.popleft()]
        self.clock += max(0.0, timeout_s)
        return []

    def poll(self, subs, timeout_s):
        self.clock += timeout_s
        return []

    def server_bad(self) -> int:
        return 0


class _Capture(logging.Handler):
    def __init__(self, out: list):
        super().__init__()
        self.out = out

    def emit(self, record):
        self.out.append((record.levelname, record.getMessage()))


class NodeHarness:
    """Build a node on a :class:`MockBus`, run its ``setup``, then drive it event by event.

    Parameters
    ----------
    node_cls : type of Node
    name : str, optional
        Default: the class name in lower case.
    namespace : str
    params : dict
        Parameter overrides (validated as in a launch).
    """

    def __init__(
        self,
        node_cls: type[Node],
        *,
        name: str | None = None,
        namespace: str = "",
        params: dict[str, Any] | None = None,
    ):
        self.bus = MockBus()
        self.node = node_cls(
            name or node_cls.__name__.lower(), namespace=namespace, params=params, bus=self.bus
        )
        self.logs: list[tuple[str, str]] = []
        log = self.node.log
        log.handlers[:] = [_Capture(self.logs)]
        log.setLevel(logging.DEBUG)
        log.propagate = False
        self.node.setup()

    def full(self, name: str) -> str:
        return self.node._resolve(name)

    def published(self, topic: str) -> list[Message]:
        """Messages the node published on ``topic`` (relative or full name), after the codec."""
        return self.bus.sent.get(self.full(topic), [])

    def feed(self, events: Iterable[Event]) -> None:
        """Run the node's :meth:`~Node.run` over exactly these events (for loop-style nodes)."""
        node = self.node
        script = list(events)

        def scripted():
            for ev in script:
                if node.stopping and not isinstance(ev, Stop):
                    break
                yield ev

        node.events = scripted  # type: ignore[method-assign]
        try:
            node.run()
        except NodeStopping:  # as in a process: a wait cut short by the stop ends the node normally
            pass
        finally:
            del node.events

    def deliver(self, topic: str, msg: Message) -> None:
        """``msg`` arrives on ``topic`` (as the node named it): round-trips the codec, then one event."""
        self.feed([Received(topic, roundtrip(msg, self.full(topic)))])

    def deliver_raw(self, topic: str, frames: list[bytes]) -> None:
        """Raw frames arrive on ``topic``: a bad message is logged and counted like in the real loop."""
        sub = self.node._subs[topic]
        try:
            msg = decode(frames, topic=sub.full, expect=sub.msg_type)
        except MessageError as exc:
            self.node._bad(topic, exc)
            return
        self.feed([Received(topic, msg)])

    def queue(self, topic: str, msg: Message) -> None:
        """Make ``msg`` available to :meth:`Node.wait_for` on ``topic``."""
        self.node._subs[topic].source.queue.append(roundtrip(msg, self.full(topic)))

    def advance(self, seconds: float) -> list[str]:
        """Move the virtual clock by ``seconds``, firing due timers in order; returns the timers fired."""
        end = self.bus.clock + seconds
        fired = []
        while not self.node.stopping:
            timers = [t for t in self.node._timers.values() if t.next_s <= end]
            if not timers:
                break
            t = min(timers, key=lambda t: t.next_s)
            self.bus.clock = max(self.bus.clock, t.next_s)
            t.next_s += t.period_s
            fired.append(t.name)
            if t.name.startswith("_"):
                t.callback()
            else:
                self.feed([Tick(t.name, int(self.bus.clock * 1e9))])
        self.bus.clock = max(self.bus.clock, end)
        return fired

    def call(self, service: str, request: Message) -> Message:
        """Call the node's service handler as a client would (codec both ways)."""
        full = self.full(service)
        req_type, resp_type, handler = self.bus.handlers[full]
        reply = handler(roundtrip(request, full))
        if type(reply) is not resp_type:
            raise MessageError(
                full, "reply", f"handler returned {type(reply).__name__}, expected {resp_type.TYPE!r}"
            )
        return roundtrip(reply, full)

    def on_call(self, service: str, responder: Callable[[Message], Message]) -> None:
        """Answer the node's calls of ``service`` with ``responder(request)`` (none set: the call times
        out)."""
        self.bus.responders[self.full(service)] = responder

    def stop(self, reason: str = "harness") -> None:
        """Send :class:`Stop` through the loop and run ``teardown``."""
        self.node.stop(reason)
        self.feed([Stop(reason)])
        self.node.teardown()
