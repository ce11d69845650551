"""Unit-test a node without processes or sockets (like dora's ``MockNode``): the node's own event loop
(:meth:`Node.run` over :meth:`Node.events`, the loop a process runs) over :class:`MockBus`, a bus with a
virtual clock.

::

    from polarstripe.runtime.testing import NodeHarness

    def test_talker_counts():
        h = NodeHarness(Talker, params={"rate_hz": 10})
        h.advance(0.35)                              # virtual time: fires the 0.1 s timer 3 times
        assert [m.text for m in h.published("chatter")] == ["hello 0", "hello 1", "hello 2"]
        assert h.call("talker/reset", Empty()).ok

How the harness drives the loop: each of :meth:`~NodeHarness.advance`, :meth:`~NodeHarness.deliver` and
:meth:`~NodeHarness.call` runs the node's ``run()`` until the virtual clock reaches a horizon (now, or now +
the seconds to advance) with nothing left to hand over; then the mock bus's ``poll`` hands control back to
the test (:class:`Paused`) and the loop's generator ends there, without a :class:`Stop`. The next call
starts the loop again where the node's state left it (timers, subscriptions). Waiting in the loop costs no
real time: ``poll`` moves the clock to the next timer.

* :meth:`~NodeHarness.advance` also hands over what :meth:`~NodeHarness.queue` put on the node's
  subscriptions (one message per subscription per loop turn, as if they arrived one after another);
* :meth:`~NodeHarness.deliver` hands over exactly one message, at once (queued ones stay queued);
* :meth:`~NodeHarness.call` has the loop answer one service request;
* :meth:`~NodeHarness.queue` only puts a message on a subscription, where :meth:`Node.wait_for` and
  :meth:`Node.take` (or the loop, during :meth:`~NodeHarness.advance`) find it;
* :meth:`~NodeHarness.feed` runs ``run()`` over a script of events instead (for loop-style nodes).

Every message crosses the real codec (encode then decode), so a field of the wrong type fails here as it
would on the wire. Logs are kept in :attr:`NodeHarness.logs` as ``(level, text)``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from polarstripe.msgs import Message, MessageError, decode
from polarstripe.runtime.mock_bus import MockBus, MockSource, Paused, Pending, roundtrip
from polarstripe.runtime.node import Event, Node, NodeStopping, Stop, Tick

CALL_LIMIT_S = 120.0
"""How long :meth:`NodeHarness.call` runs the loop for a deferred reply before giving up [s]."""
CALL_STEP_S = 0.005
"""The steps [s] in which it does, virtual time kept in step with real time."""


class _Capture(logging.Handler):
    def __init__(self, out: list):
        super().__init__()
        self.out = out

    def emit(self, record):
        self.out.append((record.levelname, record.getMessage()))


class NodeHarness:
    """Build a :class:`MockBus`, the node on it, run its ``setup``, then drive its loop (module docstring).

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
        name = name or node_cls.__name__.lower()
        self.node = node_cls(name, namespace=namespace, params=params, bus=self.bus)
        self.logs: list[tuple[str, str]] = []
        log = self.node.log
        log.handlers[:] = [_Capture(self.logs)]
        log.setLevel(logging.DEBUG)
        log.propagate = False
        self._fired: list[str] = []
        self._stop_delivered = self._torn_down = False
        self.node.events = self._events  # type: ignore[method-assign]  # the node's own, observed
        self.node.setup()
        self.node.ready = True

    def full(self, name: str) -> str:
        return self.node.resolve(name)

    def published(self, topic: str) -> list[Message]:
        """Messages the node published on ``topic`` (relative or full name), after the codec."""
        return self.bus.sent.get(self.full(topic), [])

    # ---- driving the loop --------------------------------------------------------------------------------
    def _events(self) -> Iterator[Event]:
        """The node's :meth:`Node.events`, noting the timers fired and whether its Stop went out."""
        for event in type(self.node).events(self.node):
            if isinstance(event, Tick):
                self._fired.append(event.timer)
            elif isinstance(event, Stop):
                self._stop_delivered = True
            yield event

    def _run(self, horizon: float, *, drain: bool) -> None:
        """Run the node's ``run()`` until ``horizon`` with nothing left to hand over (or until it stops)."""
        if self._stop_delivered:
            return
        bus = self.bus
        bus.horizon, bus.drain = horizon, drain
        try:
            self.node.run()
        except Paused:
            pass
        except NodeStopping:  # as in a process: a wait cut short by the stop ends the node normally
            pass
        finally:
            bus.horizon, bus.drain = None, False

    def advance(self, seconds: float) -> list[str]:
        """Run the loop for ``seconds`` of virtual time: due timers fire in order, queued messages are
        handed over; returns the names of the timers fired."""
        end = self.bus.clock + seconds
        self._fired = []
        if not self.node.stopping:
            self._run(end, drain=True)
        self.bus.clock = max(self.bus.clock, end)
        return self._fired

    def deliver(self, topic: str, msg: Message) -> None:
        """``msg`` arrives on ``topic`` (as the node named it), through the codec; the loop handles it now."""
        sub = self.node._subs[topic]
        self._hand_over(sub.source, roundtrip(msg, sub.full))

    def deliver_raw(self, topic: str, frames: list[bytes]) -> None:
        """Raw frames arrive on ``topic``: a bad message is logged and counted like in the real loop."""
        sub = self.node._subs[topic]
        try:
            item = decode(frames, topic=sub.full, expect=sub.msg_type)
        except MessageError as exc:
            sub.source.stats.bad += 1
            item = exc
        self._hand_over(sub.source, item)

    def _hand_over(self, source: MockSource, item: Message | MessageError) -> None:
        if self.node.stopping:  # a stopping node's loop takes nothing more
            return
        self.bus.urgent.append((source, item))
        self._run(self.bus.clock, drain=False)
        self.bus.urgent.clear()

    def queue(self, topic: str, msg: Message) -> None:
        """Put ``msg`` on subscription ``topic``: :meth:`Node.wait_for`, :meth:`Node.take` and (during
        :meth:`advance`) the loop find it."""
        sub = self.node._subs[topic]
        sub.source.queue.append(roundtrip(msg, sub.full))

    def request(self, service: str, request: Message) -> Pending:
        """Put a request to the node's service ``service`` (codec) where its loop answers it the next time
        it runs (e.g. from a fake peer while a long piece of work is under way); returns its
        :class:`Pending`."""
        full = self.full(service)
        pending = Pending(full, roundtrip(request, full), self.bus.handlers[full][1])
        self.bus.requests.append(pending)
        return pending

    def call(self, service: str, request: Message) -> Message:
        """Call the node's service as a client would (codec both ways): the loop answers it. For a
        deferred reply the loop runs on, queued messages handed over, until it comes (``CALL_LIMIT_S`` at
        most), its virtual clock never ahead of real time: such work waits on stages, cameras and other
        processes, which run in real time. The handler's exception is raised here (a real client would get
        a ``ServiceError``)."""
        pending = self.request(service, request)
        if not self.node.stopping:
            self._run(self.bus.clock, drain=False)
        t0, real0 = self.bus.clock, time.monotonic()
        while not pending.done and not self._stop_delivered and self.bus.clock - t0 < CALL_LIMIT_S:
            ahead = (self.bus.clock - t0) - (time.monotonic() - real0)
            if ahead > 0:  # never ahead of real time: the work waits on devices and processes that are not
                time.sleep(ahead)
            self._run(self.bus.clock + CALL_STEP_S, drain=True)
        self.bus.answer()  # a stopped loop answers nothing; the harness still does
        return pending.result()

    def feed(self, events: Iterable[Event]) -> None:
        """Run the node's :meth:`~Node.run` over exactly these events (a script, for loop-style nodes)."""
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
        except NodeStopping:
            pass
        finally:
            node.events = self._events  # type: ignore[method-assign]

    # ---- fake peers --------------------------------------------------------------------------------------
    def on_call(self, service: str, responder: Callable[[Message], Message]) -> None:
        """Answer the node's calls of ``service`` with ``responder(request)`` (none set: the call times
        out)."""
        self.bus.responders[self.full(service)] = responder

    def on_publish(self, topic: str, listener: Callable[[Message], Any]) -> None:
        """Call ``listener(msg)`` with each message the node publishes on ``topic`` (after the codec), as it
        is published: a fake peer, e.g. one that :meth:`queue`\\ s its answer."""
        self.bus.listeners.setdefault(self.full(topic), []).append(listener)

    def stop(self, reason: str = "harness") -> None:
        """Stop the node: its loop gets the :class:`Stop` event (once), then ``teardown`` runs (once)."""
        self.node.stop(reason)
        self._run(self.bus.clock, drain=False)
        if not self._torn_down:
            self._torn_down = True
            self.node.teardown()
