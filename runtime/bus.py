"""The bus: publishers, subscribers and services over ZeroMQ, with explicit endpoints and no threads.

Wire of a topic message: ``[topic, header, *buffers]`` (see :mod:`polarstripe.msgs.codec`). A node binds one
PUB socket (all its topics) and one ROUTER socket (all its services) at endpoints the launcher assigns:
``ipc://…`` on one host, ``tcp://host:port`` between hosts, optionally encrypted with CURVE and, with an
allow-list of client keys, authenticated (ZAP, :mod:`polarstripe.runtime.auth`).

* :class:`PubSocket` binds; :meth:`PubSocket.publisher` gives a :class:`Publisher` for one topic and type.
  It stamps ``seq`` (per topic, from 0) and ``stamp_ns``. Send never blocks; above ``hwm`` queued messages per
  subscriber ZeroMQ drops, and the subscriber sees the gap in ``seq``.
* :class:`Subscriber` connects to one or more PUB endpoints (it survives a publisher restart: ZeroMQ
reconnects).
  ``mode="latest"`` keeps only the newest message of what has arrived (live views); ``mode="all"`` delivers
  every message and counts sequence gaps (recorders). A bad message is counted and returned as a
  :class:`~polarstripe.msgs.MessageError`, never raised from :meth:`Subscriber.take`.
* Arrays of 64 KiB or more go zero-copy; a socket's close waits until ZeroMQ has ended it, so the process
  can free them and exit (:mod:`.zero_copy`; docs/architecture.md "What an exit guarantees").
* On one host, large buffers can travel through a shared-memory ring instead (``PubSocket(shm_slots=…)``,
  ``Subscriber(shm="copy"|"view")``; :mod:`.shm_bus`): the subscriber gets the same message.
* :class:`ServiceServer` (ROUTER) and :class:`ServiceClient` (DEALER) do request/reply with a timeout; after a
  timeout the client drops its socket, so a late reply or a queued request cannot leak into the next call.

Nothing here starts a thread (but the ZAP authenticator of an allow-list, :mod:`.auth`): a node polls the
sockets in its own loop (``Subscriber.socket``, ``ServiceServer.socket``).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import msgpack
import zmq
from polarstripe.msgs import DEFAULT_MAX_BYTES, Message, MessageError, encode
from polarstripe.msgs.codec import decode_views
from polarstripe.runtime.bus_keys import (  # noqa: F401  (importable from here, as before)
    BusError,
    BusTimeout,
    CurveKeys,
    ServiceError,
    ServiceTimeout,
    _apply_curve,
    apply_curve,
)
from polarstripe.runtime.shm_bus import LEASE, MARK, RingTake, ShmOffer, local
from polarstripe.runtime.zero_copy import ZeroCopyGuard

RECONNECT_MAX_S = 1.0
"""A subscriber retries a lost publisher's endpoint at 0.1 s, doubling up to this: a publisher started again
is heard by every subscriber within this of its bind (what it publishes before is lost to them)."""

Mode = str  # "latest" | "all"
_SNDMORE = zmq.SNDMORE
MODES = ("latest", "all")


def _bind(sock: zmq.Socket, endpoint: str) -> str:
    if endpoint.startswith("ipc://"):
        os.makedirs(os.path.dirname(endpoint[6:]) or ".", exist_ok=True)
    try:
        sock.bind(endpoint)
    except zmq.ZMQError as exc:
        sock.close(0)
        raise BusError(f"cannot bind {endpoint}: {exc}") from None
    return sock.getsockopt_string(zmq.LAST_ENDPOINT)


def _connect(sock: zmq.Socket, endpoint: str) -> None:
    try:
        sock.connect(endpoint)
    except zmq.ZMQError as exc:
        raise BusError(f"cannot connect to {endpoint}: {exc}") from None


class _SocketOwner:
    """Owns ``self.socket``: ``close()`` (no linger) and the context manager."""

    socket: zmq.Socket

    def close(self) -> None:
        self.socket.close(0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class PubSocket(_SocketOwner):
    """One bound PUB socket carrying any number of topics.

    Parameters
    ----------
    endpoint : str
        ``ipc:///path`` or ``tcp://host:port`` (port 0 or ``*`` picks a free port; see :attr:`endpoint`).
    hwm : int
        Messages queued per subscriber before ZeroMQ drops (the subscriber counts the gap). It also bounds
        how stale a slow ``latest`` subscriber can be, and the memory a stalled subscriber costs
        (100 frames of 2.6 MB = 262 MB).
    curve : CurveKeys, optional
        Encrypt with CURVE (server side).
    shm_slots : int
        On an ipc or inproc endpoint, > 0 offers the shared-memory ring form of every topic, with rings of
        this many slots (:attr:`shm`, :mod:`.shm_bus`); ignored elsewhere.
    """

    def __init__(
        self,
        endpoint: str,
        *,
        hwm: int = 100,
        curve: CurveKeys | None = None,
        ctx: zmq.Context | None = None,
        shm_slots: int = 0,
    ):
        offer = shm_slots > 0 and local(endpoint)
        self.socket = (ctx or zmq.Context.instance()).socket(zmq.XPUB if offer else zmq.PUB)
        self.socket.linger = 0
        self.socket.sndhwm = hwm
        _apply_curve(self.socket, curve, server=True)
        self.endpoint = _bind(self.socket, endpoint)
        self.guard = ZeroCopyGuard(self.socket)
        self.shm = ShmOffer(self.socket, shm_slots) if offer else None
        self._topics: dict[str, Publisher] = {}

    def close(self, linger_s: float = 0.0) -> None:
        """Close; ``linger_s`` > 0 gives what is still queued (a node's last heartbeat) that long to leave.
        Returns once ZeroMQ has ended the socket (at most ``linger_s`` + 1 s), so the arrays it was sending
        zero-copy may be freed (runtime/zero_copy.py). The shared-memory rings are unlinked."""
        self.guard.close(linger_s)
        if self.shm is not None:
            self.shm.close()

    def publisher(self, topic: str, msg_type: type[Message]) -> Publisher:
        """The publisher of ``topic`` (full name, e.g. ``/rig/camera/frame``) for messages of ``msg_type``."""
        pub = self._topics.get(topic)
        if pub is None:
            pub = self._topics[topic] = Publisher(self, topic, msg_type)
        elif pub.msg_type is not msg_type:
            raise BusError(f"topic {topic!r} already publishes {pub.msg_type.TYPE!r}, not {msg_type.TYPE!r}")
        return pub

    @property
    def topics(self) -> dict[str, type[Message]]:
        return {t: p.msg_type for t, p in self._topics.items()}


class Publisher:
    """Publishes one topic. Made by :meth:`PubSocket.publisher`."""

    def __init__(self, sock: PubSocket, topic: str, msg_type: type[Message]):
        self.topic, self.msg_type = topic, msg_type
        self._sock, self._offer = sock.socket, sock.shm
        self._topic_b = topic.encode()
        self.seq = 0  # sequence number of the next message
        self.published = 0

    def publish(self, msg: Message, *, stamp_ns: int | None = None) -> int:
        """Send ``msg`` (arrays without a copy); returns its sequence number.

        ``stamp_ns`` defaults to the message header's stamp, or now if that is 0. Raises
        :class:`MessageError` if ``msg`` is not a ``msg_type`` or a field does not match its type.
        """
        if type(msg) is not self.msg_type:
            raise MessageError(
                self.topic, "type", f"expected {self.msg_type.TYPE!r}, got {type(msg).__name__}"
            )
        seq = self.seq
        frames = encode(msg, topic=self.topic, seq=seq, stamp_ns=stamp_ns)
        plain = True
        if self._offer is not None:  # each form only while someone subscribes to it
            plain, ring = self._offer.wants(self._topic_b)
            if ring:
                self._offer.send(self._topic_b, frames)
        if plain:
            send = self._sock.send  # part by part: send_multipart's checks cost ~1 µs a part
            send(self._topic_b, _SNDMORE)
            last = len(frames) - 1
            send(frames[0], _SNDMORE if last else 0)
            for i in range(1, last + 1):
                send(frames[i], _SNDMORE if i < last else 0, copy=False)  # pyzmq copies parts < 64 KiB
        self.seq = seq + 1
        self.published += 1
        return seq


@dataclass
class SubscriberStats:
    received: int = 0  # good messages taken off the socket
    delivered: int = 0  # messages handed to the caller (latest mode skips older ones)
    skipped: int = 0  # older messages replaced by a newer one in latest mode (by design, not loss)
    bad: int = 0  # messages that failed to decode
    gaps: int = 0  # messages missing according to seq (lost in transit)
    restarts: int = 0  # times seq went backwards (the publisher restarted)
    overwritten: int = 0  # of the gaps: ring slots reused before they were read (shm)
    last_error: str = ""

    def as_dict(self) -> dict[str, int]:
        return {k: v for k, v in self.__dict__.items() if isinstance(v, int)}


class Subscriber(_SocketOwner):
    """Receives one topic from one or more publishers' endpoints.

    Parameters
    ----------
    endpoints : list of str
        PUB endpoints to connect to (more can be added with :meth:`connect`).
    topic : str
        Full topic name; only this exact topic is delivered.
    msg_type : type of Message, optional
        The expected type; other types count as bad. None accepts any registered type.
    mode : {"latest", "all"}
        ``latest``: :meth:`take` returns only the newest arrived message. ``all``: every message, gaps
        counted.
    hwm : int, optional
        Receive queue [messages]; default 4 for latest, unlimited (0) for all.
    max_bytes : int
        Messages larger than this are rejected (counted as bad).
    shm : {"", "copy", "view"}
        Receive the shared-memory ring form (every publisher must offer it: ipc or inproc, ``shm_slots``):
        ``copy`` copies each buffer out of its slot (a message like any other); ``view`` gives views of the
        slot with a lease (:func:`.shm_bus.lease_of`) that the user checks after using the bytes (the
        recorder, runtime/bag.py). A slot reused before it is read counts as a gap.
    """

    def __init__(
        self,
        endpoints: list[str] | tuple[str, ...],
        topic: str,
        msg_type: type[Message] | None = None,
        *,
        mode: Mode = "latest",
        hwm: int | None = None,
        max_bytes: int = DEFAULT_MAX_BYTES,
        curve: CurveKeys | None = None,
        ctx: zmq.Context | None = None,
        shm: str = "",
    ):
        if mode not in MODES or shm not in ("", "copy", "view"):
            raise BusError(f"topic {topic!r}: mode must be one of {MODES}, got {mode!r}; shm one of "
                           f"'', 'copy', 'view', got {shm!r}")
        self.topic, self.msg_type, self.mode, self.max_bytes = topic, msg_type, mode, max_bytes
        self.shm = shm
        self._ring = RingTake(copy=shm == "copy") if shm else None
        self._topic_b = (MARK if shm else b"") + topic.encode()
        self.socket = (ctx or zmq.Context.instance()).socket(zmq.SUB)
        self.socket.linger = 0
        self.socket.rcvhwm = (4 if mode == "latest" else 0) if hwm is None else hwm
        self.socket.reconnect_ivl = 100
        self.socket.reconnect_ivl_max = round(RECONNECT_MAX_S * 1000)
        _apply_curve(self.socket, curve, server=False)
        self.socket.setsockopt(zmq.SUBSCRIBE, self._topic_b)
        self.endpoints: list[str] = []
        for ep in endpoints:
            self.connect(ep)
        self.stats = SubscriberStats()
        self._last_seq: int | None = None

    def connect(self, endpoint: str) -> None:
        if self._ring is not None and not local(endpoint):
            raise BusError(f"topic {self.topic!r}: shared memory needs a publisher on this host, "
                           f"not {endpoint}")
        if endpoint not in self.endpoints:
            _connect(self.socket, endpoint)
            self.endpoints.append(endpoint)

    def _read(self, flags: int = 0) -> Message | MessageError | None:
        """Read one whole message off the socket (``zmq.Again`` if none with ``NOBLOCK``) and decode it;
        None for another topic sharing our prefix.

        Part by part, each a ``zmq.Frame`` whose ``more`` flag says if another follows (``recv_multipart``
        asks the socket with ``getsockopt(RCVMORE)``, ~1 µs a part); every part is read, so a malformed
        message never leaves parts behind for the next read."""
        recv = self.socket.recv
        part = recv(flags, copy=False)
        topic_b = part.bytes  # small: cheaper than a view
        head, bufs, lease = None, [], None
        if self._ring is not None:
            while part.more:
                part = recv(copy=False)
                bufs.append(part)
            if topic_b != self._topic_b:
                return None
            head, bufs, lease = self._ring.resolve(bufs)
            if bufs is None:
                return self._overwritten(head)
        while part.more:
            part = recv(copy=False)  # the rest of a message is always there once its first part is
            if head is None:
                head = part.bytes
            else:
                bufs.append(part.buffer)  # a flat byte view of the frame: no copy
        if topic_b != self._topic_b:  # a longer topic sharing our prefix
            return None
        try:
            if head is None:
                raise MessageError(self.topic, "header", "empty message (no header frame)")
            msg = decode_views(head, bufs, topic=self.topic, expect=self.msg_type, max_bytes=self.max_bytes)
        except MessageError as exc:
            self.stats.bad += 1
            self.stats.last_error = str(exc)
            return exc
        st = self.stats
        st.received += 1
        seq, last = msg.header.seq, self._last_seq
        if last is not None:
            if seq > last + 1:
                st.gaps += seq - last - 1
            elif seq <= last:
                st.restarts += 1
        self._last_seq = seq
        if self._ring is not None:
            self._ring.seen()
            if lease is not None:
                msg.__dict__[LEASE] = lease
        return msg

    def _overwritten(self, head: bytes | None) -> None:
        """A ring slot reused before it was read: a gap (its seq taken from the header)."""
        st = self.stats
        st.gaps += 1
        st.overwritten += 1
        try:
            self._last_seq = int(msgpack.unpackb(head)[3])
        except Exception:  # a header that does not decode: the gap is still counted
            pass
        return None

    @property
    def unseen_overwritten(self) -> int:
        """Overwritten messages that a count of ``seq`` gaps over the delivered ones cannot see (before the
        first, after the last): a recorder adds them to its own count."""
        return 0 if self._ring is None else self._ring.unseen

    def close(self) -> None:
        super().close()
        if self._ring is not None:
            self._ring.close()

    def take(self, limit: int = 1000) -> list[Message | MessageError]:
        """Everything that has arrived, without waiting (at most ``limit`` messages read off the socket).

        In ``latest`` mode only the newest good message is returned (older ones are counted as skipped).
        Bad messages are returned as :class:`MessageError` (already counted in :attr:`stats`).
        """
        out: list = []
        for _ in range(limit):
            try:
                item = self._read(zmq.NOBLOCK)
            except zmq.Again:
                break
            if item is not None:
                out.append(item)
        if self.mode == "latest":
            good = [m for m in out if not isinstance(m, MessageError)]
            if len(good) > 1:
                self.stats.skipped += len(good) - 1
                out = [m for m in out if isinstance(m, MessageError)] + good[-1:]
        self.stats.delivered += sum(1 for m in out if not isinstance(m, MessageError))
        return out

    def recv(self, timeout_s: float | None = None) -> Message:
        """Wait for the next good message (``None`` waits forever). Bad messages are counted and skipped.

        Raises :class:`BusTimeout` (a :class:`TimeoutError`) after ``timeout_s`` with nothing good received.
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            if self.mode == "latest":
                for item in self.take():
                    if not isinstance(item, MessageError):
                        return item
            elif deadline is None or self.socket.poll(0):  # all mode: one at a time, blocking if no deadline
                item = self._read()
                if item is not None and not isinstance(item, MessageError):
                    self.stats.delivered += 1
                    return item
                continue
            if deadline is None:
                self.socket.poll(None)
                continue
            left = deadline - time.monotonic()
            if left <= 0:
                raise BusTimeout(f"topic {self.topic!r}: nothing received within {timeout_s} s")
            self.socket.poll(int(left * 1000) + 1)

