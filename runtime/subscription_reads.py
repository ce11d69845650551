"""Reading a node's subscriptions outside its loop: :meth:`SubscriptionReads.wait_for` (block until a
matching message, a timeout, a stop or a lost peer) and :meth:`SubscriptionReads.take` (what has arrived,
nothing dropped).

:class:`SubscriptionReads` is a mixin of :class:`~polarstripe.runtime.node.Node` (it uses the node's
subscriptions, bus, clock, stop reason, bad-message count and, for ``peers``, its watch:
runtime/liveness.py).
"""

from __future__ import annotations

from collections.abc import Callable

from polarstripe.msgs import Message, MessageError
from polarstripe.runtime.bus import BusTimeout
from polarstripe.runtime.events import NodeError, NodeStopping

__all__ = ["STOP_CHECK_S", "SubscriptionReads"]

STOP_CHECK_S = 0.05
"""How often a blocking :meth:`Node.wait_for` looks whether the node was told to stop [s]."""


class SubscriptionReads:
    """The part of :class:`~polarstripe.runtime.node.Node` that reads its subscriptions outside the loop."""

    def wait_for(self, topic: str, match: Callable[[Message], bool] = lambda m: True, timeout_s: float = 1.0,
                 *, peers: tuple[str, ...] | list[str] = ()):
        """Block until a message on subscribed ``topic`` satisfies ``match``; non-matching messages before it
        are dropped, those after it stay queued for the next call or the loop. Nothing else is handled
        meanwhile (no service is answered): keep it for scripts and short waits.

        Raises :class:`~polarstripe.runtime.bus.BusTimeout` (a ``TimeoutError``) naming the topic
        after ``timeout_s``, or :class:`NodeStopping` within ~``STOP_CHECK_S`` of the node being told to
        stop (SIGINT, SIGTERM, :meth:`Node.stop`; also at once if it already was). With ``peers`` (node names,
        after :meth:`Node.watch`) it raises :class:`~polarstripe.runtime.liveness.PeerLost` naming the first
        of them that is lost.
        """
        sub = self._sub(topic, "wait_for")
        if peers and self.liveness is None:
            raise NodeError(f"node {self.name!r}: wait_for(peers=...) needs watch() first")
        deadline = self.now() + timeout_s
        while True:
            if self._stop_reason is not None:
                raise NodeStopping(self.name, sub.full, self._stop_reason)
            # short slices: a signal does not cut a zmq poll short (pyzmq resumes it after the handler)
            for item in self._bus.take(sub.source, min(max(0.0, deadline - self.now()), STOP_CHECK_S)):
                if isinstance(item, MessageError):
                    self._bad(topic, item)
                    continue
                self._feed(topic, item)
                if match(item):
                    return item
            if peers:
                self.check_peers(peers, topic)
            if self.now() >= deadline:
                raise BusTimeout(
                    f"node {self.name!r}: no matching message on {sub.full!r} within {timeout_s} s"
                )

    def take(self, topic: str, timeout_s: float = 0.0) -> list[Message]:
        """Every message that has arrived on subscribed ``topic`` and the loop has not handled yet (in
        ``latest`` mode the newest), waiting up to ``timeout_s`` for the first; bad ones are logged and
        counted. Unlike :meth:`wait_for`, nothing is dropped."""
        sub = self._sub(topic, "take")
        out: list[Message] = []
        wait = timeout_s
        while items := self._bus.take(sub.source, wait):
            wait = 0.0
            for item in items:
                if isinstance(item, MessageError):
                    self._bad(topic, item)
                else:
                    self._feed(topic, item)
                    out.append(item)
        return out

    def _sub(self, topic: str, what: str):
        """The node's subscription of ``topic``; NodeError naming ``what`` needs it when there is none."""
        sub = self._subs.get(topic)
        if sub is None:
            raise NodeError(f"node {self.name!r}: {what}({topic!r}) needs a subscription first")
        return sub
