"""Services over ZeroMQ: a ROUTER server for any number of named services, DEALER clients with timeouts.

Request frames (DEALER → ROUTER): ``[name, request_id, header, *buffers]``; reply: ``[name, request_id, b"ok",
header, *buffers]`` or ``[name, request_id, b"error", text]``. After a timeout the client drops its socket, so
a late reply or a queued request cannot leak into the next call. No threads: the node loop polls
:attr:`ServiceServer.socket`. (Also importable from :mod:`polarstripe.runtime.bus`.)
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zmq
from polarstripe.msgs import DEFAULT_MAX_BYTES, Message, MessageError, decode, encode
from polarstripe.runtime import auth
from polarstripe.runtime.bus import (
    BusError,
    CurveKeys,
    ServiceError,
    ServiceTimeout,
    _apply_curve,
    _bind,
    _connect,
    _SocketOwner,
)
from polarstripe.runtime.node_bus import Deferred
from polarstripe.runtime.zero_copy import ZeroCopyGuard

Handler = Callable[[Message], "Message | Deferred"]


@dataclass
class _Service:
    name: str
    req_type: type[Message]
    resp_type: type[Message]
    handler: Handler
    calls: int = 0
    errors: int = 0


@dataclass
class ServerStats:
    requests: int = 0
    bad: int = 0
    errors: int = 0
    last_error: str = ""
    per_service: dict[str, int] = field(default_factory=dict)


class ServiceServer(_SocketOwner):
    """Serves any number of named services on one bound ROUTER socket.

    Request frames (from a DEALER): ``[name, request_id, header, *buffers]``; reply:
    ``[name, request_id, b"ok", header, *buffers]`` or ``[name, request_id, b"error", text]``.
    """

    def __init__(
        self,
        endpoint: str,
        *,
        curve: CurveKeys | None = None,
        max_bytes: int = DEFAULT_MAX_BYTES,
        ctx: zmq.Context | None = None,
    ):
        self.socket = (ctx or zmq.Context.instance()).socket(zmq.ROUTER)
        self.socket.linger = 0
        self.socket.router_mandatory = False
        _apply_curve(self.socket, curve, server=True)
        self.endpoint = _bind(self.socket, endpoint)
        self.guard = ZeroCopyGuard(self.socket)  # replies' arrays go zero-copy (runtime/zero_copy.py)
        self.max_bytes = max_bytes
        self.services: dict[str, _Service] = {}
        self.stats = ServerStats()

    def close(self) -> None:
        self.guard.close(0)

    def add(self, name: str, req_type: type[Message], resp_type: type[Message], handler: Handler) -> None:
        """Serve ``name``: ``handler(request) -> reply``; an exception becomes an error reply with its
        text."""
        if name in self.services:
            raise BusError(f"service {name!r} is already served here")
        self.services[name] = _Service(name, req_type, resp_type, handler)

    def handle_ready(self, limit: int = 100) -> list[MessageError | Exception]:
        """Answer every waiting request (up to ``limit``); returns the problems met (already counted)."""
        problems: list = []
        for _ in range(limit):
            try:
                frames = self.socket.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            problem = self._handle(frames)
            if problem is not None:
                problems.append(problem)
        return problems

    def _handle(self, frames: list):
        st = self.stats
        st.requests += 1
        if len(frames) < 4:
            st.bad += 1
            st.last_error = f"malformed request ({len(frames)} frames)"
            return MessageError("<service>", "request", st.last_error)
        ident, name_f, rid = frames[0].bytes, frames[1].bytes, frames[2].bytes
        name = name_f.decode("utf-8", "replace")
        svc = self.services.get(name)

        def reply(status: bytes, payload: list) -> None:
            self.socket.send_multipart([ident, name_f, rid, status, *payload], copy=False)

        if svc is None:
            st.bad += 1
            st.last_error = f"service {name!r} is not served at {self.endpoint}"
            reply(b"error", [st.last_error.encode()])
            return BusError(st.last_error)
        try:
            req = decode(frames[3:], topic=name, expect=svc.req_type, max_bytes=self.max_bytes)
        except MessageError as exc:
            st.bad += 1
            st.last_error = str(exc)
            reply(b"error", [str(exc).encode()])
            return exc
        svc.calls += 1
        st.per_service[name] = st.per_service.get(name, 0) + 1
        seq = svc.calls - 1
        try:
            resp = svc.handler(req)
        except Exception as exc:  # the handler's failure goes back to the caller, the node keeps serving
            return self._answer(svc, seq, reply, None, exc)
        if isinstance(resp, Deferred):  # answered later, from the node's loop
            resp.bind(lambda msg, exc: self._answer(svc, seq, reply, msg, exc))
            return None
        return self._answer(svc, seq, reply, resp, None)

    def _answer(self, svc: _Service, seq: int, reply: Callable, resp: Message | None, exc: Exception | None):
        """Send the reply (or the error) of one request; returns the problem, if any (counted)."""
        if exc is None:
            try:
                if type(resp) is not svc.resp_type:
                    raise MessageError(svc.name, "reply", f"handler returned {type(resp).__name__}, "
                                       f"expected {svc.resp_type.TYPE!r}")
                payload = encode(resp, topic=svc.name, seq=seq)
            except Exception as e:
                exc = e
        if exc is not None:
            st = self.stats
            svc.errors += 1
            st.errors += 1
            st.last_error = f"service {svc.name!r}: {type(exc).__name__}: {exc}"
            reply(b"error", [st.last_error.encode()])
            return exc
        reply(b"ok", payload)
        return None


_request_ids = itertools.count(1)

CHECK_S = 0.05
"""How often a call given a ``check`` calls it while it waits for the reply [s]."""


class ServiceClient:
    """Calls one service at one endpoint. Never wedges: every call has a timeout.

    Parameters
    ----------
    endpoint : str
        The serving node's ROUTER endpoint.
    name : str
        Service name (full, e.g. ``/rig/emitter/start_scan``).
    req_type, resp_type : type of Message
    timeout_s : float
        Default timeout of :meth:`call` [s].
    """

    def __init__(
        self,
        endpoint: str,
        name: str,
        req_type: type[Message],
        resp_type: type[Message],
        *,
        timeout_s: float = 2.0,
        curve: CurveKeys | None = None,
        max_bytes: int = DEFAULT_MAX_BYTES,
        ctx: zmq.Context | None = None,
    ):
        self.endpoint, self.name = endpoint, name
        self.req_type, self.resp_type = req_type, resp_type
        self.timeout_s, self.max_bytes = timeout_s, max_bytes
        self._ctx, self._curve = ctx or zmq.Context.instance(), curve
        self._name_b = name.encode()
        self.socket: zmq.Socket | None = None
        self._monitor: zmq.Socket | None = None  # hears a CURVE server refuse our key (runtime/auth.py)
        self.calls = self.timeouts = 0

    def _open(self) -> zmq.Socket:
        if self.socket is None:
            s = self._ctx.socket(zmq.DEALER)
            s.linger = 0
            s.reconnect_ivl = 100
            _apply_curve(s, self._curve, server=False)
            self._monitor = auth.watch_refusal(s) if self._curve else None
            _connect(s, self.endpoint)
            self.socket = s
        return self.socket

    def call(self, request: Message, timeout_s: float | None = None, *,
             check: Callable[[], None] | None = None) -> Message:
        """Send ``request`` and wait for the reply; with ``check``, call it every :data:`CHECK_S` while
        waiting: what it raises ends the call (runtime/client.py: the server was lost).

        Raises
        ------
        ServiceTimeout
            No reply within ``timeout_s`` (default :attr:`timeout_s`); names the service and endpoint.
        ServiceError
            The server answered with an error.
        MessageError
            The request does not match ``req_type``, or the reply could not be decoded.
        """
        if type(request) is not self.req_type:
            raise MessageError(
                self.name, "type", f"expected {self.req_type.TYPE!r}, got {type(request).__name__}"
            )
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        sock = self._open()
        rid = next(_request_ids).to_bytes(8, "little")
        self.calls += 1
        out = [self._name_b, rid, *encode(request, topic=self.name, seq=self.calls - 1)]
        deadline = time.monotonic() + timeout_s
        # a DEALER with no peer (a server that refused our key drops the connection) blocks its send: wait for
        # room within the deadline; copied: a request is sent once (zero-copy buys nothing), and a socket
        # dropped after a timeout is not waited for (runtime/zero_copy.py)
        sent = False
        while True:
            left = deadline - time.monotonic()
            wait = left if check is None else min(left, CHECK_S)
            if not sent and left > 0 and sock.poll(max(1, int(wait * 1000)), zmq.POLLOUT):
                try:
                    sock.send_multipart(out, flags=zmq.NOBLOCK)
                    sent = True
                except zmq.Again:   # the room went again: wait on
                    pass
                continue
            if left <= 0 or not sent or not sock.poll(max(1, int(wait * 1000))):
                if check is not None and left > 0 and time.monotonic() < deadline:  # ask, then wait on
                    try:
                        check()
                    except BaseException:
                        self._drop()  # the reply must not leak into the next call
                        raise
                    continue
                self.timeouts += 1
                note = auth.refusal_note(self._monitor, self._curve.public if self._curve else b"")
                self._drop()  # a late reply or our queued request must not leak into the next call
                raise ServiceTimeout(
                    f"service {self.name!r} at {self.endpoint}: no reply within {timeout_s} s{note}"
                )
            frames = sock.recv_multipart(copy=False)
            if len(frames) < 3 or frames[1].bytes != rid:
                continue  # a reply to an earlier, abandoned call
            status = frames[2].bytes
            if status == b"ok":
                return decode(frames[3:], topic=self.name, expect=self.resp_type, max_bytes=self.max_bytes)
            text = frames[3].bytes.decode("utf-8", "replace") if len(frames) > 3 else "error"
            raise ServiceError(f"service {self.name!r} at {self.endpoint}: {text}")

    def _drop(self) -> None:
        if self._monitor is not None:
            self.socket.disable_monitor()
            self._monitor.close(0)
            self._monitor = None
        if self.socket is not None:
            self.socket.close(0)
            self.socket = None

    def close(self) -> None:
        self._drop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
