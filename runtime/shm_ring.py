"""Frames through shared memory on one host: a ring of slots in one POSIX shared-memory segment
(:mod:`multiprocessing.shared_memory`), written by one publisher and read by any process of this host
(docs/architecture.md, "Frames through shared memory").

A slot is a 64-byte head ``[begin: u64][end: u64]`` and the message's buffers, each at a 64-byte boundary.
Writing is a seqlock: the writer stores ``begin = ticket``, copies the buffers, then stores ``end = ticket``
(tickets count the ring's writes from 1, so a ticket names one write of one slot). A reader told
``(slot, ticket)`` over ZeroMQ uses the bytes it copied or wrote out only if ``end == ticket`` before and
``begin == ticket`` after: a slot reused meanwhile fails the check, and the message is dropped and counted
as a gap, never passed on torn. (Each ticket is one aligned 8-byte store, and x86-64 keeps stores in order.)

Segments: named ``psring_<publisher pid>_<random>``; the publisher unlinks its rings when it closes, its
resource tracker (:mod:`multiprocessing.resource_tracker`) unlinks them if it dies, and a new ring sweeps
away the rings of publishers that are no longer alive (a publisher killed together with its tracker).
A reader attaches without registering with its own tracker (Python 3.11 registers every attach, and the
tracker of a reader that exits would unlink the publisher's segment and warn; 3.13 has ``track=False``):
:func:`attach`. (A reader started by ``multiprocessing`` from the publisher shares its tracker; the bus's
processes are started by the launcher, each with its own.)
"""

from __future__ import annotations

import mmap
import os
import secrets
import sys
from multiprocessing import resource_tracker
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path

import numpy as np
from polarstripe.runtime.graph import pid_alive

HEAD = 64  # bytes before a slot's first buffer: begin and end tickets, padded to a cache line
ALIGN = 64
PREFIX = "psring_"
DEFAULT_SLOTS = 32
"""Slots of a publisher's ring per topic: how many frames a reader may fall behind before the oldest is
overwritten (about a second of a 30 fps camera; 84 MB of 2.6 MB frames, reserved while the publisher runs)."""


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def slot_bytes(lengths: list[int]) -> int:
    """The bytes buffers of these lengths take in a slot (each starts at a 64-byte boundary)."""
    return sum(_aligned(n) for n in lengths)


def sweep_dead(directory: str = "/dev/shm") -> list[str]:
    """Unlink the rings of publishers that are no longer alive (their pid is in the name); the names
    removed. Linux keeps POSIX shared memory in ``/dev/shm``; elsewhere this does nothing."""
    gone = []
    try:
        names = [p.name for p in Path(directory).iterdir() if p.name.startswith(PREFIX)]
    except OSError:
        return gone
    for name in names:
        pid = name[len(PREFIX):].partition("_")[0]
        if pid.isdigit() and not pid_alive(int(pid)):
            try:
                os.unlink(os.path.join(directory, name))
                gone.append(name)
            except OSError:
                pass
    return gone


def attach(name: str) -> SharedMemory:
    """Map the publisher's segment ``name`` without handing it to this process's resource tracker (the
    workaround accepted for Python < 3.13: attach, then unregister). ``FileNotFoundError`` if it is gone."""
    if sys.version_info >= (3, 13):
        return SharedMemory(name, track=False)
    shm = SharedMemory(name)
    if name[len(PREFIX):].partition("_")[0] != str(os.getpid()):  # our own ring: the tracker keeps it
        resource_tracker.unregister(shm._name, "shared_memory")  # noqa: SLF001 (the name as registered)
    return shm


class RingWriter:
    """The publisher's ring of ``slots`` slots of ``capacity`` bytes each: a new segment whose pages are
    allocated as its first lap writes them, or all at once with ``prefault`` (zero-filled: ~0.5 s for 84 MB
    of cold memory on the 2-CPU development VM, a stall a live camera would rather spread out)."""

    def __init__(self, slots: int, capacity: int, *, prefault: bool = False):
        if slots < 1 or capacity < 1:
            raise ValueError(f"a ring needs slots >= 1 and capacity >= 1, got {slots}, {capacity}")
        sweep_dead()
        self.slots, self.capacity = int(slots), _aligned(int(capacity))
        self.stride = HEAD + self.capacity
        self.shm = SharedMemory(
            name=f"{PREFIX}{os.getpid()}_{secrets.token_hex(4)}", create=True, size=self.slots * self.stride
        )
        self.name = self.shm.name
        self._bytes = np.ndarray((self.slots * self.stride,), np.uint8, self.shm.buf)
        if prefault:
            self._bytes[:] = 0
        self._tickets = np.ndarray((self.slots * self.stride // 8,), np.uint64, self.shm.buf)
        self.ticket = 0  # of the last write

    def write(self, bufs: list) -> tuple[int, int, list[int]]:
        """Copy ``bufs`` (byte buffers) into the next slot; ``(slot, ticket, lengths)`` for the readers."""
        views = [b if isinstance(b, memoryview) and b.format == "B" and b.ndim == 1
                 else memoryview(b).cast("B")
                 for b in bufs]
        lengths = [v.nbytes for v in views]
        if slot_bytes(lengths) > self.capacity:
            raise ValueError(f"{slot_bytes(lengths)} bytes do not fit a slot of {self.capacity}")
        self.ticket = ticket = self.ticket + 1
        slot = (ticket - 1) % self.slots
        t = slot * self.stride // 8
        self._tickets[t] = ticket  # begin: readers of the slot's last ticket now see it reused
        off = slot * self.stride + HEAD
        for v, n in zip(views, lengths, strict=True):
            self._bytes[off:off + n] = np.frombuffer(v, np.uint8)
            off += _aligned(n)
        self._tickets[t + 1] = ticket  # end: the slot holds this ticket's bytes
        return slot, ticket, lengths

    def close(self) -> None:
        """Unmap and unlink (readers that have it mapped keep their mapping until they let it go)."""
        self._bytes = self._tickets = None
        self.shm.close()
        try:
            self.shm.unlink()
        except FileNotFoundError:  # swept or unlinked by hand
            pass


class Lease:
    """A message whose buffers are views of a ring slot: :meth:`valid` says whether the slot still holds
    its ticket (check it after using the bytes; before is not enough)."""

    __slots__ = ("_tickets", "_t", "ticket")

    def __init__(self, tickets: np.ndarray, t: int, ticket: int):
        self._tickets, self._t, self.ticket = tickets, t, ticket

    def valid(self) -> bool:
        return int(self._tickets[self._t]) == self.ticket


class RingReader:
    """The readers' side of publishers' rings: attached on first use, the ``keep`` most recently used
    mapped until :meth:`close` (an older one, of a publisher that restarted or outgrew its ring, is let
    go)."""

    def __init__(self, keep: int = 4):
        self.keep = keep
        self._rings: dict[str, tuple[SharedMemory, np.ndarray, np.ndarray, int]] = {}

    def _ring(self, name: str, stride: int):
        ring = self._rings.get(name)
        if ring is None:
            while len(self._rings) >= self.keep:
                self._let_go(next(iter(self._rings)))
            shm = attach(name)
            # frombuffer keeps a view that holds the mapping (np.ndarray(buffer=…) would not): arrays made
            # from the slot keep it, and closing the segment under them fails (BufferError), never unmaps.
            data = np.frombuffer(shm.buf, np.uint8)
            # Map every page now (one read each): a ring is reused, so this is the mapping its first lap
            # would make; a page first touched by a writev costs a fault inside it (twice the write's CPU).
            int(data[:: mmap.PAGESIZE].sum())
            ring = self._rings[name] = (shm, data, np.frombuffer(shm.buf, np.uint64), stride)
        elif next(reversed(self._rings)) != name:  # most recently used last
            self._rings[name] = self._rings.pop(name)
        return ring

    def _let_go(self, name: str) -> None:
        shm = self._rings.pop(name)[0]  # this reader's own views go first
        try:
            shm.close()
        except BufferError:  # a message still views it: the mapping goes with the last such view
            shm._mmap = None  # noqa: SLF001 (so that SharedMemory.__del__ does not try again and warn)

    def views(self, name: str, stride: int, slot: int, ticket: int, lengths: list[int]):
        """``(buffers as read-only byte views of the slot, its Lease)``, or None when the slot no longer
        holds ``ticket`` (overwritten) or the segment is gone (the publisher closed it)."""
        try:
            _, data, tickets, _ = self._ring(name, stride)
        except (FileNotFoundError, ValueError):
            return None
        t = slot * stride // 8
        if (slot + 1) * stride > data.size or int(tickets[t + 1]) != ticket or int(tickets[t]) != ticket:
            return None
        out, off = [], slot * stride + HEAD
        for n in lengths:
            v = data[off:off + n]
            v.flags.writeable = False
            out.append(memoryview(v))
            off += _aligned(n)
        return out, Lease(tickets, t, ticket)

    def copies(self, name: str, stride: int, slot: int, ticket: int, lengths: list[int]):
        """The buffers copied out of the slot (one ``memcpy`` each), or None as :meth:`views` (also when
        the slot was reused during the copy)."""
        got = self.views(name, stride, slot, ticket, lengths)
        if got is None:
            return None
        views, lease = got
        out = [memoryview(np.frombuffer(v, np.uint8).copy()) for v in views]
        return out if lease.valid() else None

    def close(self) -> None:
        """Let every segment go (a mapping still viewed by a message is unmapped when that message goes)."""
        for name in list(self._rings):
            self._let_go(name)
