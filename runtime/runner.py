"""Running a node as a process: its ZeroMQ bus (from the graph file or explicit endpoints), logging,
signals, heartbeat, and an orderly close. ``polarstripe node`` and the launcher's children end up in
:func:`run_node`.

Order: the params are typed and checked (a bad one fails before any socket is bound), the bus is built
(:class:`ZmqNodeBus`, the real :class:`~polarstripe.runtime.node_bus.NodeBus`), the node is constructed on it,
then ``setup``, the loop (``run``), ``teardown`` and the bus closes."""

from __future__ import annotations

import importlib
import math
import os
import threading
import time
from pathlib import Path
from typing import Any

import zmq
from polarstripe.errors import PolarstripeError
from polarstripe.msgs import Heartbeat, Message
from polarstripe.runtime import bus as zbus
from polarstripe.runtime.auth import log_refusals_as
from polarstripe.runtime.client import ServerWatch
from polarstripe.runtime.graph import load_graph, pub_endpoints, runs_dir, shm_offered
from polarstripe.runtime.liveness import HeartbeatThread, incarnation
from polarstripe.runtime.node import Node, NodeStopping
from polarstripe.runtime.node_bus import Handler
from polarstripe.runtime.params import build_params
from polarstripe.runtime.process import (
    GuardedClient,
    StopGuard,
    early_signal_seen,
    early_signals,
    install_logging,
    install_signals,
    release_signals,
)
from polarstripe.runtime.service import ServiceClient, ServiceServer
from polarstripe.runtime.shm_bus import local


def load_node_class(spec: str) -> type[Node]:
    """``"package.module:Class"`` (or ``"package.module"`` whose ``NODE`` is the class) → the class.

    Raises :class:`PolarstripeError` naming the spec if the module or class is missing.
    """
    module_name, _, cls_name = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise PolarstripeError(f"node {spec!r}: module {exc.name!r} not found") from None
    obj = getattr(module, cls_name or "NODE", None)
    if not (isinstance(obj, type) and issubclass(obj, Node)):
        what = f"class {cls_name!r}" if cls_name else "NODE attribute naming its Node class"
        raise PolarstripeError(f"node {spec!r}: module {module_name!r} has no {what} (a Node subclass)")
    return obj


class ZmqNodeBus:
    """The real :class:`~polarstripe.runtime.node_bus.NodeBus`: one PUB socket, one ROUTER socket (made when
    the first service is served), subscribers connected to the publishers the graph lists (and ``connect``),
    service clients pointed by the graph (or ``services``); ``time.monotonic`` as the clock."""

    def __init__(
        self,
        name: str,
        *,
        pub: str,
        srv: str,
        graph: dict | None = None,
        connect: list[str] = (),
        services: dict[str, str] | None = None,
        curve: zbus.CurveKeys | None = None,
        pub_hwm: int = 100,
        shm_slots: int = 0,
    ):
        self.name, self.graph, self.curve = name, graph or {}, curve
        self.ctx = zmq.Context.instance()
        self.pub_socket = zbus.PubSocket(pub, hwm=pub_hwm, curve=curve, shm_slots=shm_slots)
        self.pub_lock = threading.Lock()  # the heartbeat thread publishes on the same PUB socket
        self._srv_endpoint = srv
        self.server: ServiceServer | None = None
        self.connect = list(connect)
        self.service_endpoints = dict(services or {})
        self.subscribers: list[zbus.Subscriber] = []
        self.clients: list[ServiceClient] = []
        self.poller = zmq.Poller()
        self.guard: StopGuard | None = None  # set by run_node: stop signals cut service calls short
        self.watch: ServerWatch | None = None  # made with the first client that knows its server

    now = staticmethod(time.monotonic)

    def publisher(self, topic: str, msg_type: type[Message]):
        return _LockedPublisher(self.pub_socket.publisher(topic, msg_type), self.pub_lock)

    def subscribe(
        self, topic: str, msg_type: type[Message], mode: str, max_bytes: int, queue: int | None = None,
        shm: str = "",
    ) -> zbus.Subscriber:
        endpoints = pub_endpoints(self.graph, topic) + self.connect
        client_curve = self.curve.client() if self.curve else None  # this host's own key pair
        if shm and self.graph.get("nodes") and not shm_offered(self.graph, topic):
            shm = ""  # shared memory only where every publisher offers it (a node by hand: its caller says)
        if shm:
            endpoints = [e for e in endpoints if local(e)]
        sub = zbus.Subscriber(
            endpoints, topic, msg_type, mode=mode, hwm=queue, max_bytes=max_bytes, curve=client_curve, shm=shm
        )
        self.subscribers.append(sub)
        self.poller.register(sub.socket, zmq.POLLIN)
        return sub

    def serve(self, service: str, req: type[Message], resp: type[Message], handler: Handler) -> None:
        if self.server is None:
            self.server = ServiceServer(self._srv_endpoint, curve=self.curve)
            self.poller.register(self.server.socket, zmq.POLLIN)
        self.server.add(service, req, resp, handler)

    def client(self, service: str, req: type[Message], resp: type[Message], timeout_s: float):
        endpoint = self.service_endpoints.get(service) or self.graph.get("services", {}).get(service, {}).get(
            "endpoint"
        )
        if not endpoint:
            raise zbus.BusError(
                f"service {service!r} is not served by any node of this launch "
                f"(known: {', '.join(sorted(self.graph.get('services', {}))) or 'none'})"
            )
        client_curve = self.curve.client() if self.curve else None  # this host's own key pair
        c = ServiceClient(endpoint, service, req, resp, timeout_s=timeout_s, curve=client_curve)
        self.clients.append(c)
        return c if self.guard is None else GuardedClient(c, self.guard)

    def server_watch(self, heartbeat_topic: str) -> ServerWatch | None:
        if self.watch is None and self.graph.get("nodes"):
            client_curve = self.curve.client() if self.curve else None
            self.watch = ServerWatch(pub_endpoints(self.graph, heartbeat_topic), heartbeat_topic,
                                     curve=client_curve)
        return self.watch

    def poll(self, sources: list[zbus.Subscriber], timeout_s: float) -> list[tuple[zbus.Subscriber, list]]:
        # Round up: rounding down would spin through the last millisecond before every timer.
        ready = dict(self.poller.poll(max(0, math.ceil(timeout_s * 1000))))
        if self.server is not None and self.server.socket in ready:
            self.server.handle_ready()
        return [(s, s.take()) for s in sources if s.socket in ready]

    def take(self, sub: zbus.Subscriber, timeout_s: float) -> list:
        """For ``wait_for``: one message at a time in ``all`` mode, so nothing after a match is taken off the
        socket (and lost); ``latest`` mode keeps its meaning, the newest of what has arrived."""
        if sub.socket.poll(max(0, math.ceil(timeout_s * 1000))):
            return sub.take(limit=1 if sub.mode == "all" else 1000)
        return []

    def service_stats(self) -> tuple[int, int, int]:
        st = self.server.stats if self.server else None
        return (st.requests, st.errors, st.bad) if st else (0, 0, 0)

    def close(self) -> None:
        for s in self.subscribers:
            s.close()
        for c in self.clients:
            c.close()
        if self.watch is not None:
            self.watch.close()
        if self.server is not None:
            self.server.close()
        self.pub_socket.close(linger_s=0.25)  # the last heartbeat ("exiting") and log lines get out


def default_endpoints(name: str) -> tuple[str, str]:
    """Endpoints of a node started by hand (no launcher): ipc sockets in ``<runs>/standalone/``."""
    d = runs_dir().parent / "standalone"
    return f"ipc://{d}/{name}.pub", f"ipc://{d}/{name}.srv"


def run_node(
    spec: str,
    *,
    name: str | None = None,
    namespace: str = "",
    params: dict[str, Any] | None = None,
    graph_file: str | None = None,
    pub: str | None = None,
    srv: str | None = None,
    connect: list[str] = (),
    services: dict[str, str] | None = None,
) -> int:
    """Run one node until SIGINT/SIGTERM or :meth:`Node.stop`; returns its exit code.

    With ``graph_file`` (the launcher's), the node's endpoints and its peers come from the graph; otherwise
    from ``pub``/``srv`` (default :func:`default_endpoints`), ``connect`` (PUB endpoints to subscribe to)
    and ``services`` (service name → ROUTER endpoint).
    """
    try:
        with early_signals():  # a Ctrl-C during the node module's import ends it at once (exit 130)
            cls = load_node_class(spec)
    except ImportError:
        if early_signal_seen():  # the KeyboardInterrupt landed in an extension's init, which reports it as
            raise KeyboardInterrupt from None  # "ImportError: initialization failed": still the user's stop
        raise
    graph = load_graph(graph_file) if graph_file else {}
    name = name or cls.__name__.lower()
    entry = graph.get("nodes", {}).get(name, {})
    if graph and not entry:
        raise PolarstripeError(f"node {name!r} is not in graph {graph_file}")
    namespace = namespace or graph.get("namespace", "")
    d_pub, d_srv = default_endpoints(name)
    pub = pub or entry.get("pub") or d_pub
    srv = srv or entry.get("srv") or d_srv
    curve = zbus.CurveKeys.from_env()  # this host's keys and allow-list (docs/hardware.md "Security")
    if curve is not None and curve.allow is not None:
        log_refusals_as(name)
    typed = build_params(cls.Params, params or {}, node=name)  # a bad param fails before anything binds
    bus = ZmqNodeBus(
        name,
        pub=pub,
        srv=srv,
        graph=graph,
        connect=list(connect),
        services=services,
        curve=curve,
        pub_hwm=typed.pub_hwm,
        shm_slots=int(entry.get("shm_slots") or 0),
    )
    node: Node | None = None
    try:
        node = cls(name, namespace=namespace, params=typed, bus=bus)
        node.incarnation = incarnation()  # the launcher's respawn count ($POLARSTRIPE_INCARNATION)
        install_logging(node, bus)
        bus.guard = install_signals(node)
        _run(node, bus)
    except KeyboardInterrupt:
        if node is None:
            raise
        node.exit_code = node.exit_code or 130
    finally:
        release_signals()
        bus.close()
        for endpoint in (pub, srv):  # libzmq removes them on close, but not if the process ends first
            if endpoint.startswith("ipc://"):
                Path(endpoint[6:]).unlink(missing_ok=True)
    return node.exit_code


def _run(node: Node, bus: ZmqNodeBus) -> None:
    """The heartbeat thread (runtime/liveness.py: it beats while a handler is busy; ``starting`` until setup
    is done, so a peer waiting for this node knows it is alive but not ready), ``setup``, the loop,
    ``teardown`` and the last heartbeat (``exiting``: peers know at once that the node stopped)."""
    hb_pub = bus.publisher(node.resolve("heartbeat"), Heartbeat)
    beat = node.params.heartbeat_s > 0
    beats = None
    if beat:
        beats = HeartbeatThread(node.beat_period_s, lambda: hb_pub.publish(node.heartbeat())).start()
    try:
        with bus.guard.interruptible("setup"):  # a stop signal ends a long setup (the planner plans)
            node.setup()
        node.ready = True
    except NodeStopping as exc:
        if beats is not None:
            beats.stop()
            hb_pub.publish(node.heartbeat(exiting=True))
        node.log.info("stopped during setup (%s)", exc.reason)
        try:
            node.teardown()  # what setup had opened (a half set-up node may lack attributes)
        except Exception as err:  # noqa: BLE001 - the node is stopping either way
            node.log.debug("teardown after an interrupted setup: %s", err)
        return
    except BaseException:  # a setup that failed: no beats from a node on its way out
        if beats is not None:
            beats.stop()
        raise
    node.log.info("started (pid %d, pub %s)", os.getpid(), bus.pub_socket.endpoint)
    try:
        node.run()
    except NodeStopping as exc:  # a wait cut short by the stop: the node ends as it was told to
        node.log.debug("%s", exc)
    finally:
        if beats is not None:
            beats.stop()
        node.teardown()
        if beat:
            hb_pub.publish(node.heartbeat(exiting=True))
        node.log.info("stopped (%s)", node.stop_reason or "loop ended")


class _LockedPublisher:
    """A bus publisher whose ``publish`` holds the PUB socket's lock (ZeroMQ sockets are not thread-safe;
    the heartbeat thread and log lines from worker threads share the socket with the loop)."""

    def __init__(self, pub, lock: threading.Lock):
        self._pub, self._lock = pub, lock
        self.topic, self.msg_type = pub.topic, pub.msg_type

    def publish(self, msg: Message, *, stamp_ns: int | None = None) -> int:
        with self._lock:
            return self._pub.publish(msg, stamp_ns=stamp_ns)

    def __getattr__(self, name):  # seq, published, … of the wrapped publisher
        return getattr(self._pub, name)
