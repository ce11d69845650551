"""The node contract: what a :class:`~polarstripe.runtime.node.Node` needs from a bus, and nothing more.

A node never builds sockets or reads a clock itself; it is given a bus when it is constructed
(``Node(name, bus=...)``) and goes through it for everything. Two buses implement :class:`NodeBus`:

* :class:`~polarstripe.runtime.runner.ZmqNodeBus`, the real one: one PUB socket, one ROUTER socket for the
  node's services, SUB sockets and DEALER clients pointed by the launch graph, ``time.monotonic`` as clock;
* :class:`~polarstripe.runtime.mock_bus.MockBus`, the harness's: no sockets, every message through the codec,
  a virtual clock that only moves when the node waits.

The bus owns the sockets and the clock; the node owns the loop (:meth:`Node.events`), the timers, the
counters and the names (the bus only sees full names, e.g. ``/rig/camera/frame``). Node code uses the node's
public calls (``publisher``, ``subscribe``, ``serve``, ``client``, ``every``, ``wait_for``, ``take``,
``now``, ``graph``), never the bus directly.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

from polarstripe.msgs import Message, MessageError

Item = Message | MessageError
"""What a subscription yields: a decoded message, or the error of one that failed to decode."""


class Deferred:
    """A service reply that comes later. A handler returns one instead of its reply when the answer needs
    work that the loop steps (the polarizer's calibration), then calls :meth:`reply` (or :meth:`fail`) once,
    from the loop, when the work is done. The caller waits as for any reply, up to its own timeout; the
    node answers its other services meanwhile. The bus checks the reply's type as for a direct one."""

    def __init__(self):
        self.done = False
        self._sink: Callable[[Message | None, Exception | None], Any] | None = None
        self._outcome: tuple[Message | None, Exception | None] | None = None

    def reply(self, msg: Message) -> None:
        self._settle(msg, None)

    def fail(self, exc: Exception) -> None:
        """Answer with an error (the caller gets a ``ServiceError`` with its text)."""
        self._settle(None, exc)

    def bind(self, sink: Callable[[Message | None, Exception | None], Any]) -> None:
        """For the bus: where the outcome goes (at once if it is already known)."""
        self._sink = sink
        if self._outcome is not None:
            sink(*self._outcome)

    def _settle(self, msg: Message | None, exc: Exception | None) -> None:
        if self.done:
            raise RuntimeError("this deferred service reply was already given")
        self.done = True
        if self._sink is not None:
            self._sink(msg, exc)
        else:
            self._outcome = (msg, exc)


Handler = Callable[[Message], "Message | Deferred"]


class BusPublisher(Protocol):
    """Publishes one topic (full name) with one message type."""

    topic: str
    msg_type: type[Message]

    def publish(self, msg: Message, *, stamp_ns: int | None = None) -> int:
        """Send ``msg`` without blocking; its sequence number (``MessageError`` if not a ``msg_type``)."""
        ...


class BusSource(Protocol):
    """One subscription's receiving end, as the bus made it (:meth:`NodeBus.subscribe`)."""

    mode: str  # "latest" | "all"
    stats: Any  # received delivered skipped bad gaps restarts (SubscriberStats)


class BusClient(Protocol):
    """A client of one service (full name): request/reply with a timeout."""

    def call(self, request: Message, timeout_s: float | None = None, *,
             check: Callable[[], None] | None = None) -> Message:
        """The reply; ``ServiceTimeout`` without one in time, ``ServiceError`` if the handler failed; what
        ``check`` (called every few tens of ms while waiting) raises."""
        ...

    def close(self) -> None: ...


@runtime_checkable
class NodeBus(Protocol):
    """Everything a node asks of a bus (all names are full names)."""

    graph: dict
    """The launch graph the node runs in (``{}`` when started by hand or in the harness)."""

    def now(self) -> float:
        """The node's clock [s]: monotonic; virtual in the harness. Timers and timeouts use it."""
        ...

    def publisher(self, topic: str, msg_type: type[Message]) -> BusPublisher: ...

    def subscribe(
        self, topic: str, msg_type: type[Message], mode: str, max_bytes: int, queue: int | None = None,
        shm: str = "",
    ) -> BusSource:
        """Receive ``topic``; ``queue``: messages received ahead of the node (None: the mode's default);
        ``shm``: ``"copy"`` or ``"view"`` asks for the shared-memory ring form where every publisher offers it
        (runtime/shm_bus.py), ``""`` the socket."""
        ...

    def serve(self, service: str, req: type[Message], resp: type[Message], handler: Handler) -> None:
        """Answer ``service`` with ``handler``; requests are answered inside :meth:`poll`, or later when
        the handler returns a :class:`Deferred`."""
        ...

    def client(self, service: str, req: type[Message], resp: type[Message], timeout_s: float) -> BusClient:
        """A client of ``service``; ``BusError`` if no node of the launch serves it."""
        ...

    def server_watch(self, heartbeat_topic: str) -> Any:
        """The liveness of the launch's nodes for its clients (a ``runtime.client.ServerWatch`` of the beats
        on ``heartbeat_topic``, one per bus), or None where the bus has none to watch (the harness)."""
        ...

    def poll(self, sources: Sequence[BusSource], timeout_s: float) -> list[tuple[BusSource, list[Item]]]:
        """Wait up to ``timeout_s`` for messages on ``sources``; answer waiting service requests; return
        what arrived, per source (sources with nothing are left out). The one place the loop waits."""
        ...

    def take(self, source: BusSource, timeout_s: float) -> list[Item]:
        """Wait up to ``timeout_s`` for ``source`` alone (services are not answered meanwhile). In ``all``
        mode one message at a time, so nothing after it is taken off the socket; in ``latest`` mode the
        newest of what has arrived."""
        ...

    def service_stats(self) -> tuple[int, int, int]:
        """``(requests, errors, bad)`` of the node's services so far (for the heartbeat)."""
        ...

    def close(self) -> None: ...
