"""The bus's shared-memory path: large buffers of a topic go through a ring (:mod:`.shm_ring`) and ZeroMQ
carries only the slot's name, number and ticket (docs/architecture.md, "Frames through shared memory").

Opt-in per publisher/subscriber pair on one host. A publisher offers it when its PUB socket is bound at an
``ipc://`` or ``inproc://`` endpoint with ``shm_slots`` > 0 (the launcher's ipc nodes: the graph's
``shm_slots``); its socket is then an XPUB, which tells it who subscribes to what. A subscriber asks for it
by subscribing to the *ring form* of a topic, ``b"\\x01" + topic`` (no topic starts with that byte, so the
two forms never match each other's subscriptions), and only where every publisher of the topic offers it.

Wire of the ring form: ``[b"\\x01" + topic, ref, header, *buffers]``; ``ref`` empty: the buffers follow
inline (a message under :data:`MIN_BYTES`); else msgpack ``[segment, stride, slot, ticket, [lengths]]`` and
the buffers are in the slot. The header is the plain form's, so the subscriber decodes the same message
type. The publisher sends each form only while someone subscribes to it: a recorder alone costs one copy
into the ring instead of the socket's two (into the kernel and out of it).
"""

from __future__ import annotations

import logging

import msgpack
import zmq
from polarstripe.runtime.shm_ring import DEFAULT_SLOTS, Lease, RingReader, RingWriter, slot_bytes

__all__ = ["DEFAULT_SLOTS", "LEASE", "MARK", "MIN_BYTES", "RingTake", "ShmOffer", "lease_of", "local"]

MARK = b"\x01"
MIN_BYTES = 64 << 10
"""Messages whose buffers are smaller than this travel inline in the ring form (a slot is not worth it)."""
RING_BYTES = 256 << 20
"""A ring has fewer slots (at least 2) where ``shm_slots`` of its messages would take more than this: a topic
of large, rare messages (composites) does not reserve hundreds of MB."""
LEASE = "_shm_lease"
"""Where a message read as views of a ring slot keeps its :class:`~.shm_ring.Lease` (``msg.__dict__``)."""

_packb = msgpack.Packer(use_bin_type=True).pack
log = logging.getLogger(__name__)
_SNDMORE = zmq.SNDMORE


def local(endpoint: str) -> bool:
    """Whether ``endpoint`` is on this host by construction (ipc or inproc)."""
    return endpoint.startswith(("ipc://", "inproc://"))


def lease_of(msg) -> Lease | None:
    """The lease of a message received as views of a ring slot (``Subscriber(shm="view")``), else None."""
    return msg.__dict__.get(LEASE)


class ShmOffer:
    """A PUB socket's side of the ring form: who subscribes (the XPUB's subscription messages), one ring
    per topic (made for the first large message a ring subscriber needs, made anew when a message outgrows
    its slots), unlinked on :meth:`close`."""

    def __init__(self, socket: zmq.Socket, slots: int = DEFAULT_SLOTS):
        self.socket, self.slots = socket, int(slots)
        self.max_bytes = RING_BYTES  # per ring (0: no limit)
        self.prefixes: set[bytes] = set()  # subscribed prefixes, plain and ring form
        self.rings: dict[bytes, RingWriter] = {}
        self.failed: dict[bytes, str] = {}  # topics whose ring could not be made: why
        self._wants: dict[bytes, tuple[bool, bool]] = {}

    def wants(self, topic_b: bytes) -> tuple[bool, bool]:
        """``(plain form, ring form)``: whether anyone subscribes to each form of ``topic_b`` now."""
        sock = self.socket
        while sock.get(zmq.EVENTS) & zmq.POLLIN:  # subscription changes (first subscriber in, last out)
            ev = sock.recv()
            if ev[:1] == b"\x01":
                self.prefixes.add(ev[1:])
            elif ev[:1] == b"\x00":
                self.prefixes.discard(ev[1:])
            self._wants.clear()
        got = self._wants.get(topic_b)
        if got is None:
            ring_b = MARK + topic_b
            got = self._wants[topic_b] = (
                any(topic_b.startswith(p) for p in self.prefixes),
                any(ring_b.startswith(p) and p[:1] == MARK for p in self.prefixes),
            )
        return got

    def send(self, topic_b: bytes, frames: list) -> None:
        """Send ``frames`` (``[header, *buffers]``) in the ring form of ``topic_b``."""
        send = self.socket.send
        bufs = [memoryview(b) for b in frames[1:]]
        need = slot_bytes([b.nbytes for b in bufs])
        ring = self.rings.get(topic_b)
        if need >= MIN_BYTES and (ring is None or ring.capacity < need) and topic_b not in self.failed:
            try:
                ring = self.reserve(topic_b, need)
            except OSError as exc:  # /dev/shm full or not writable: this topic goes inline, said once
                self.failed[topic_b] = str(exc)
                log.warning("topic %s: no shared-memory ring (%s); its ring form carries the bytes inline",
                            topic_b.decode(errors="replace"), exc)
        send(MARK + topic_b, _SNDMORE)
        if need < MIN_BYTES or topic_b in self.failed:
            send(b"", _SNDMORE)
            last = len(frames) - 1
            for i, f in enumerate(frames):
                send(f, _SNDMORE if i < last else 0, copy=i == 0)
            return
        slot, ticket, lengths = ring.write(bufs)
        send(_packb([ring.name, ring.stride, slot, ticket, lengths]), _SNDMORE)
        send(frames[0])

    def reserve(self, topic_b: bytes, nbytes: int, *, prefault: bool = False) -> RingWriter:
        """The ring of ``topic_b`` for messages of up to ``nbytes`` of buffers, made now if it has none that
        large (the old one is unlinked); ``prefault``: its pages allocated now (before a burst), not on its
        first lap."""
        ring = self.rings.get(topic_b)
        if ring is None or ring.capacity < nbytes:
            if ring is not None:
                ring.close()
            slots = (min(self.slots, max(2, self.max_bytes // max(nbytes, 1))) if self.max_bytes
                     else self.slots)
            ring = self.rings[topic_b] = RingWriter(slots, nbytes, prefault=prefault)
        return ring

    def close(self) -> None:
        rings, self.rings = self.rings, {}
        for ring in rings.values():
            ring.close()


class RingTake:
    """A subscriber's side of the ring form: the frames after the topic → ``(header, buffers, lease)``,
    or the header alone (``bytes``) when the slot was overwritten before it was read (a gap)."""

    def __init__(self, copy: bool):
        self.copy = copy  # copy out of the slot (a message to keep) or views with a lease (the recorder)
        self.reader = RingReader()
        self.lost = 0  # messages whose slot was reused before they were read
        self._head = self._pending = 0  # lost before the first message read, and since the last one
        self._any = False

    def seen(self) -> None:
        """A message was read whole (called by the subscriber)."""
        if self._pending and not self._any:
            self._head += self._pending
        self._pending, self._any = 0, True

    @property
    def unseen(self) -> int:
        """Lost messages a count of ``seq`` gaps over the messages read cannot see: those before the first
        and after the last."""
        return self._head + self._pending

    def resolve(self, frames: list) -> tuple:
        ref = frames[0].bytes if frames else b""
        if not ref:
            return (frames[1].bytes if len(frames) > 1 else None), [f.buffer for f in frames[2:]], None
        head = frames[1].bytes if len(frames) > 1 else None
        try:
            name, stride, slot, ticket, lengths = msgpack.unpackb(ref)
        except (ValueError, TypeError, msgpack.UnpackException):
            return head, None, None
        if self.copy:
            bufs, lease = self.reader.copies(name, stride, slot, ticket, lengths), None
        else:
            got = self.reader.views(name, stride, slot, ticket, lengths)
            bufs, lease = (None, None) if got is None else got
        if bufs is None:
            self.lost += 1
            self._pending += 1
            return head, None, None
        return head, list(bufs), lease

    def close(self) -> None:
        self.reader.close()
