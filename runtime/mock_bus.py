"""The harness's bus (runtime/testing.py): no sockets, a virtual clock, every message through the codec.
:class:`MockBus` implements the node's bus (runtime/node_bus.py); :meth:`MockBus.poll` moves the clock to
the next timer instead of waiting and raises :class:`Paused` at the harness's horizon."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from polarstripe.msgs import Message, MessageError, decode, encode
from polarstripe.runtime.bus import ServiceError, ServiceTimeout, SubscriberStats
from polarstripe.runtime.node_bus import Deferred, Handler


def roundtrip(msg: Message, topic: str = "") -> Message:
    """``msg`` after the wire: encoded and decoded (arrays become read-only views)."""
    frames = [bytes(f) if isinstance(f, bytes) else f.tobytes() for f in encode(msg, topic=topic)]
    return decode(frames, topic=topic, expect=type(msg))


class Paused(BaseException):
    """Raised by :meth:`MockBus.poll` when the harness's horizon is reached: it ends the node's loop for now
    and hands control back to the test. A ``BaseException``, so a node's ``except Exception`` lets it by."""


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
        sent = decode(frames, topic=self.topic, expect=self.msg_type)
        self.bus.sent.setdefault(self.topic, []).append(sent)
        self.seq += 1
        for listener in self.bus.listeners.get(self.topic, []):
            listener(sent)
        return self.seq - 1


class MockSource:
    """A subscription's receiving end: what has arrived (``queue``) and its statistics."""

    def __init__(self, topic: str, msg_type: type[Message], mode: str):
        self.topic, self.msg_type, self.mode = topic, msg_type, mode
        self.stats = SubscriberStats()
        self.queue: deque = deque()


class _Client:
    def __init__(self, bus: MockBus, service: str, req: type[Message], resp: type[Message], timeout_s: float):
        self.bus, self.name, self.req_type, self.resp_type = bus, service, req, resp
        self.timeout_s = timeout_s
        self.requests: list[Message] = []

    def call(self, request: Message, timeout_s: float | None = None, *, check=None) -> Message:
        request = roundtrip(request, self.name)  # (no server watch here: ``check`` is never given)
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


class Pending:
    """A request to one of the node's services (:meth:`NodeHarness.request`): ``done`` once the loop has
    answered it (at once, or later for a :class:`~polarstripe.runtime.node_bus.Deferred` reply)."""

    def __init__(self, service: str, request: Message, resp_type: type[Message]):
        self.service, self.request, self.resp_type = service, request, resp_type
        self.done = False
        self.reply: Message | None = None
        self.error: BaseException | None = None

    def settle(self, reply: Message | None, error: BaseException | None) -> None:
        self.reply, self.error, self.done = reply, error, True

    def result(self) -> Message:
        """The reply after the codec; the handler's exception is raised here (a real client would get a
        ``ServiceError``), as is a reply of the wrong type or none yet (``ServiceTimeout``)."""
        if not self.done:
            raise ServiceTimeout(f"service {self.service!r} at <harness>: not answered (yet)")
        if self.error is not None:
            raise self.error
        if type(self.reply) is not self.resp_type:
            raise MessageError(self.service, "reply", f"handler returned {type(self.reply).__name__}, "
                               f"expected {self.resp_type.TYPE!r}")
        return roundtrip(self.reply, self.service)


class MockBus:
    """The harness's :class:`~polarstripe.runtime.node_bus.NodeBus`: no sockets, a virtual clock.

    ``clock`` [s] moves only when the node waits: in :meth:`poll` up to the next timer (never past the
    harness's horizon), in :meth:`take` by the whole timeout when nothing is queued, and by a client's
    timeout when no responder answers. What the node published is in ``sent`` (full topic → messages).
    """

    def __init__(self):
        self.clock = 0.0
        self.graph: dict = {}
        self.sent: dict[str, list[Message]] = {}
        self.sources: dict[str, MockSource] = {}
        self.handlers: dict[str, tuple[type[Message], type[Message], Handler]] = {}
        self.responders: dict[str, Callable[[Message], Message]] = {}
        self.listeners: dict[str, list[Callable[[Message], Any]]] = {}
        self.clients: dict[str, _Client] = {}
        self.horizon: float | None = None  # set by the harness while it runs the loop
        self.drain = False  # hand queued messages to the loop (advance) or not (deliver, call)
        self.urgent: deque[tuple[MockSource, Message | MessageError]] = deque()
        self.requests: deque[Pending] = deque()

    def now(self) -> float:
        return self.clock

    def publisher(self, topic: str, msg_type: type[Message]) -> _Pub:
        return _Pub(self, topic, msg_type)

    def subscribe(
        self, topic: str, msg_type: type[Message], mode: str, max_bytes: int, queue: int | None = None,
        shm: str = "",
    ) -> MockSource:  # (``queue``, ``shm`` have no meaning here: the harness delivers what its test sends)
        src = self.sources[topic] = MockSource(topic, msg_type, mode)
        return src

    def serve(self, service: str, req: type[Message], resp: type[Message], handler: Handler) -> None:
        self.handlers[service] = (req, resp, handler)

    def client(self, service: str, req: type[Message], resp: type[Message], timeout_s: float) -> _Client:
        c = self.clients[service] = _Client(self, service, req, resp, timeout_s)
        return c

    def answer(self) -> None:
        """Answer the waiting service requests (the handler's exception is kept for the caller)."""
        while self.requests:
            r = self.requests.popleft()
            try:
                reply = self.handlers[r.service][2](r.request)
            except Exception as exc:  # as a server would: the node keeps running, the caller gets it
                r.settle(None, exc)
                continue
            if isinstance(reply, Deferred):
                reply.bind(r.settle)
            else:
                r.settle(reply, None)

    def poll(self, sources: Sequence[MockSource], timeout_s: float) -> list[tuple[MockSource, list]]:
        self.answer()
        if self.urgent:
            source, item = self.urgent.popleft()
            return [(source, [item])]
        if self.drain:
            ready = [(s, [s.queue.popleft()]) for s in sources if s.queue]
            if ready:
                return ready
        if self.horizon is not None:
            if self.clock >= self.horizon:
                raise Paused
            self.clock = min(self.clock + timeout_s, self.horizon)
        else:
            self.clock += timeout_s
        return []

    def take(self, source: MockSource, timeout_s: float) -> list:
        if source.queue:
            return [source.queue.popleft()]
        self.clock += max(0.0, timeout_s)
        return []

    def server_watch(self, heartbeat_topic: str) -> None:
        return None  # no processes to watch: a call waits for its responder or its timeout

    def service_stats(self) -> tuple[int, int, int]:
        return (0, 0, 0)

    def close(self) -> None:
        pass
