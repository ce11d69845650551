"""A node's service client, modelled on rclpy's ``Client``: :meth:`Client.wait_for_service`, and
:meth:`Client.call` that may retry and that fails as soon as the serving node is lost.

``Node.client(service, req, resp, timeout_s=…)`` makes one per service, types and timeout (the same object
for the same arguments: a client is a socket, and one per call grew a soak's sequencer by ~15 KB a scan).

**Its server's liveness.** Where the launch graph names the node that serves the service, the node's bus
keeps a :class:`ServerWatch`: a thread of its own reads the launch's heartbeats into a
:class:`~polarstripe.runtime.liveness.Liveness`, so beats never pile up between calls and the verdict is
current at any moment. A call waits for its reply in slices of :data:`CHECK_S` and ends with
:class:`ServiceLost` as soon as the liveness declares the server lost (no beat for 4 of its periods, 1 s by
default; its last beat said it was exiting; or it came back as a new process) — not at the call's timeout,
which may be long (a render: 30 s). A call to a server already lost fails at once. Without a graph (a node
started by hand, the harness) there is no watch and a call waits for its reply or its timeout.

**Retries** (``retry_s``): a call that timed out, or whose server was lost, is made again — after
:meth:`~Client.wait_for_service` has seen the server (back) — until ``retry_s`` after the first try; for
services that may not be up yet (the sequencer's first calls) or whose node the launch respawns.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import zmq
from polarstripe.msgs import Heartbeat, Message
from polarstripe.runtime.bus import CurveKeys, ServiceError, ServiceTimeout, Subscriber
from polarstripe.runtime.liveness import Liveness, PeerLost
from polarstripe.runtime.service import CHECK_S

__all__ = ["CHECK_S", "Client", "ServerWatch", "ServiceLost"]


class ServiceLost(ServiceError, PeerLost):
    """A call's server was lost (runtime/liveness.py) before it answered: a :class:`ServiceError` for code
    that handles a failed call, and a :class:`PeerLost` (``node``, ``reason``, ``incarnation``,
    ``respawned``) for code that recovers from a lost node."""

    def __init__(self, service: str, lost: PeerLost):
        PeerLost.__init__(self, lost.node, lost.reason, lost.incarnation, lost.respawned)
        self.service = service
        self.args = (f"service {service!r}: {lost}",)


class ServerWatch:
    """The heartbeats on ``topic`` from ``endpoints`` (a launch's nodes), read by a daemon thread into a
    :class:`~polarstripe.runtime.liveness.Liveness` on the monotonic clock; its methods may be called from
    any thread. :meth:`close` ends the thread and its socket."""

    def __init__(self, endpoints: list[str], topic: str, *, curve: CurveKeys | None = None):
        self.liveness = Liveness(time.monotonic)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, args=(list(endpoints), topic, curve),
                                        name="server-watch", daemon=True)
        self._thread.start()

    def _read(self, endpoints: list[str], topic: str, curve: CurveKeys | None) -> None:
        sub = Subscriber(endpoints, topic, Heartbeat, mode="all", curve=curve)  # this thread's socket alone
        try:
            while not self._stop.is_set():
                if sub.socket.poll(int(CHECK_S * 1000)):
                    beats = [b for b in sub.take() if isinstance(b, Heartbeat)]
                    with self._lock:
                        for beat in beats:
                            self.liveness.heard(beat)
        except zmq.ZMQError:  # the context terminated at exit: the watch ends with the process
            pass
        finally:
            sub.close()

    def lost(self, node: str) -> PeerLost | None:
        """Why ``node`` is lost, or None while it beats (or was never heard: not judged)."""
        with self._lock:
            return self.liveness.check([node])

    def ready(self, node: str) -> bool:
        """Whether ``node`` beats, done with its setup; a loss it came back from is forgiven here."""
        with self._lock:
            live = self.liveness
            peer, lost = live.peers.get(node), live.check([node])
            if lost is not None and lost.respawned:
                live.forgive(node)
                lost = live.check([node])
            return peer is not None and lost is None and not live.peers[node].starting

    def forgive(self, node: str) -> None:
        with self._lock:
            self.liveness.forgive(node)

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(1.0)


class Client:
    """A node's client of one service (see the module docstring); made by ``Node.client``.

    Parameters
    ----------
    bus_client
        The bus's client of the service (``call(request, timeout_s=None, *, check=None)``, ``close()``).
    server : str or None
        The node that serves it (from the launch graph), None when unknown.
    watch : ServerWatch or None
        The liveness of the launch's nodes; None: the call is not cut short by a loss.
    now, stopping
        The node's clock and whether the node is stopping (retries end then).
    """

    def __init__(self, bus_client, *, server: str | None = None, watch: ServerWatch | None = None,
                 now: Callable[[], float] = time.monotonic, stopping: Callable[[], bool] = lambda: False):
        self._client, self.server = bus_client, server
        self._watch = watch if server is not None else None
        self._now, self._stopping = now, stopping

    @property
    def name(self) -> str:
        return self._client.name

    @property
    def timeout_s(self) -> float:
        return self._client.timeout_s

    def wait_for_service(self, timeout_s: float) -> bool:
        """True once the serving node beats, ready (its setup done) and not lost, within ``timeout_s``; True
        at once where nothing watches it (the call will find out); False after ``timeout_s`` or when the node
        is told to stop."""
        if self._watch is None:
            return True
        deadline = self._now() + timeout_s
        while not self._watch.ready(self.server):
            if self._now() >= deadline or self._stopping():
                return False
            time.sleep(CHECK_S)
        return True

    def call(self, request: Message, timeout_s: float | None = None, *, retry_s: float = 0.0) -> Message:
        """Send ``request``, return the reply.

        Raises
        ------
        ServiceTimeout
            No reply within ``timeout_s`` (default :attr:`timeout_s`) on the last try.
        ServiceLost
            The server was lost before it answered (the last try).
        ServiceError, MessageError
            The server answered with an error; a request or reply of the wrong type (never retried).
        """
        deadline = self._now() + retry_s
        while True:
            try:
                return self._call_once(request, timeout_s)
            except (ServiceTimeout, ServiceLost):
                if self._now() >= deadline or self._stopping():
                    raise
            self.wait_for_service(max(0.0, deadline - self._now()))

    def _call_once(self, request: Message, timeout_s: float | None) -> Message:
        if self._watch is None:
            return self._client.call(request, timeout_s)
        if not self._watch.ready(self.server):  # forgives a loss the server came back from
            self._fail_if_lost()
        return self._client.call(request, timeout_s, check=self._fail_if_lost)

    def _fail_if_lost(self) -> None:
        lost = self._watch.lost(self.server)
        if lost is not None:
            raise ServiceLost(self.name, lost)

    def close(self) -> None:
        self._client.close()
