"""Zero-copy sends that the process's exit cannot outrun (docs/architecture.md, "Bus": "What a node's exit
guarantees").

``socket.send(buf, copy=False)`` hands ZeroMQ the buffer itself (pyzmq copies one under
``zmq.COPY_THRESHOLD``, 64 KiB): ZeroMQ's I/O thread writes it out after ``send`` returned, while pyzmq keeps
the buffer's object alive in a table of its garbage-collector thread (``zmq.utils.garbage``) until ZeroMQ
lets the message go. At interpreter exit, pyzmq's own exit handler stops that thread and empties the table:
the buffers of messages still queued (a slow subscriber; a socket closed with a linger, or with none while
the I/O thread is mid-write; a socket left open) are freed under the I/O thread, and its next write from them
kills the process (SIGSEGV, or SIGABRT on libzmq's "Bad address" assertion).

:class:`ZeroCopy` sends a socket's large parts tracked (``track=True``: a :class:`zmq.MessageTracker`, done
once ZeroMQ has let the part go) and keeps the trackers not done yet; :meth:`ZeroCopy.close` closes the socket
with a linger and waits, at most that linger and :data:`GRACE_S`, until ZeroMQ has let every one go (a
linger ends in ZeroMQ dropping what is left, which lets it go too). An exit handler, run before pyzmq's
(``atexit`` runs handlers in reverse order of registration), does that for every socket not closed yet.
"""

from __future__ import annotations

import atexit
import logging
import time
import weakref
from collections import deque

import zmq
import zmq.utils.garbage  # noqa: F401  (registers pyzmq's exit handler before ours: ours runs first)

__all__ = ["GRACE_S", "ZeroCopy"]

GRACE_S = 1.0
"""How long after a close's linger ZeroMQ gets to let go of the last zero-copy parts [s] (its I/O thread
ends the writes, pyzmq's thread notes the release: milliseconds, unless the machine is starved)."""

log = logging.getLogger(__name__)
_live: weakref.WeakSet[ZeroCopy] = weakref.WeakSet()
_orphans: deque = deque()  # trackers of ZeroCopy objects collected before their socket was closed


class ZeroCopy:
    """A socket's zero-copy sends, tracked until ZeroMQ lets them go (module docstring)."""

    def __init__(self, socket: zmq.Socket):
        self.socket = socket
        self.held: deque[zmq.MessageTracker] = deque()  # not done when sent; some may be done since
        self._compact_at = 64
        _live.add(self)

    def send(self, data, flags: int = 0) -> None:
        """``socket.send(data, flags, copy=False)``, its tracker kept while ZeroMQ holds the buffer."""
        tracker = self.socket.send(data, flags, copy=False, track=True)
        if not tracker.done:  # a part under the copy threshold was copied: done at once
            held = self.held
            held.append(tracker)
            if len(held) >= self._compact_at:
                self._compact()

    def send_multipart(self, parts: list) -> None:
        last = len(parts) - 1
        for i, part in enumerate(parts):
            self.send(part, zmq.SNDMORE if i < last else 0)

    def _compact(self) -> None:
        """Drop the done trackers; what ZeroMQ still holds is bounded by the socket's queues (hwm)."""
        self.held = deque(t for t in self.held if not t.done)
        self._compact_at = max(64, 2 * len(self.held))

    def close(self, linger_s: float | None = None) -> int:
        """Close the socket (what is queued gets ``linger_s`` to leave; None: the socket's own linger), then
        wait until ZeroMQ has let go of every buffer sent through here, at most the linger and
        :data:`GRACE_S`. Returns how many it still holds (0: the buffers may go; else a warning is logged)."""
        sock = self.socket
        linger_ms = (sock.linger if not sock.closed else 0) if linger_s is None else round(linger_s * 1000)
        if not sock.closed:
            sock.close(linger_ms)
        _live.discard(self)
        held, self.held = self.held, deque()
        left = _wait(held, time.monotonic() + max(linger_ms, 0) / 1000 + GRACE_S)
        if left:
            log.warning("%d zero-copy messages still held by ZeroMQ %.1f s after the close of %s",
                        left, max(linger_ms, 0) / 1000 + GRACE_S, sock)
        return left

    def __del__(self):
        # Collected with its socket still to close (the socket's own __del__, next): the exit waits on these.
        if self.held:
            _orphans.extend(t for t in self.held if not t.done)


def _wait(trackers, deadline: float) -> int:
    """Wait until every tracker is done or ``deadline`` (``time.monotonic``) passes; how many are not."""
    for t in trackers:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        try:
            t.wait(left)
        except zmq.NotDone:
            break
    return sum(1 for t in trackers if not t.done)


@atexit.register
def _close_all() -> None:
    """Before pyzmq frees what ZeroMQ still holds: close every tracked socket (its own linger) and wait."""
    for zc in list(_live):
        zc.close()
    orphans = list(_orphans)
    _orphans.clear()
    _wait(orphans, time.monotonic() + GRACE_S)
