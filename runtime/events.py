"""What a node's loop yields (:class:`Received`, :class:`Tick`, :class:`Stop`) and the errors a node raises.

Importable from :mod:`polarstripe.runtime.node` too, where :meth:`Node.events` makes them.
"""

from __future__ import annotations

from dataclasses import dataclass

from polarstripe.errors import PolarstripeError
from polarstripe.msgs import Message


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


@dataclass(frozen=True)
class Received:
    """A message arrived on ``topic`` (the name as the node declared it, e.g. ``"camera/frame"``)."""

    topic: str
    msg: Message


@dataclass(frozen=True)
class Tick:
    """Timer ``timer`` fired; ``now_ns`` is the node's clock (:meth:`Node.now`) [ns]."""

    timer: str
    now_ns: int


@dataclass(frozen=True)
class Stop:
    """The loop is ending (``reason``: ``"SIGINT"``, ``"SIGTERM"``, or the text given to
    :meth:`Node.stop`)."""

    reason: str


Event = Received | Tick | Stop
