"""Zero-copy sends that the process's exit cannot outrun (docs/architecture.md, "Bus": "What an exit
guarantees for queued messages").

``socket.send(buf, copy=False)`` hands ZeroMQ the buffer itself (pyzmq copies one under
``zmq.COPY_THRESHOLD``, 64 KiB): ZeroMQ's I/O thread writes it out after ``send`` returned, while pyzmq keeps
the buffer's object alive in a table of its garbage-collector thread (``zmq.utils.garbage``) until ZeroMQ
lets the message go. At interpreter exit, pyzmq's own exit handler stops that thread and empties the table:
the buffers of messages still queued (a slow subscriber; a socket closed with a linger, or with none while
the I/O thread is mid-write; a socket left open) are freed under the I/O thread, and its next write from them
kills the process (SIGSEGV, or SIGABRT on libzmq's "Bad address" assertion).

:class:`ZeroCopyGuard` watches a socket's end: ``zmq_close`` returns at once and ZeroMQ's reaper thread
tears the socket down later (after its linger, every queued message closed and every connection's engine
gone), which it reports on a monitor as ``EVENT_MONITOR_STOPPED`` (the only event asked for: nothing is
monitored while the socket runs). :meth:`ZeroCopyGuard.close` closes the socket with a linger and waits for
that event, at most the linger and :data:`GRACE_S`. An exit handler, run before pyzmq's (``atexit`` runs
handlers in reverse order of registration), does that for every guarded socket not closed yet. Sends stay
as they are: nothing is added per message.
"""

from __future__ import annotations

import atexit
import itertools
import logging
import os
import weakref

import zmq
import zmq.utils.garbage  # noqa: F401  (registers pyzmq's exit handler before ours: ours runs first)

__all__ = ["GRACE_S", "ZeroCopyGuard", "monitor_socket"]

GRACE_S = 1.0
"""How long after a close's linger ZeroMQ gets to end the socket [s] (its reaper and I/O threads finish the
teardown: milliseconds, unless the machine is starved)."""

log = logging.getLogger(__name__)
_live: weakref.WeakSet[ZeroCopyGuard] = weakref.WeakSet()
_monitors = itertools.count()


def monitor_socket(socket: zmq.Socket, events: int) -> zmq.Socket:
    """A monitor of ``socket`` for ``events`` on an inproc address of its own. pyzmq's default address names
    the socket's file descriptor, which the OS gives again to a later socket while ZeroMQ's reaper may still
    be ending the earlier one and its monitor: the later monitor then failed with "Address already in use"
    (seen once in a full suite)."""
    return socket.get_monitor_socket(events, addr=f"inproc://polarstripe-monitor-{os.getpid()}-{next(_monitors)}")


class ZeroCopyGuard:
    """Closes ``socket`` so that it is gone, and with it every buffer it was sending, when :meth:`close`
    returns (module docstring). Made right after the socket (the monitor is ``socket``'s only one)."""

    def __init__(self, socket: zmq.Socket):
        self.socket = socket
        self._ended = monitor_socket(socket, zmq.EVENT_MONITOR_STOPPED)
        self._ended.linger = 0
        _live.add(self)

    def close(self, linger_s: float | None = None) -> bool:
        """Close the socket (what is queued gets ``linger_s`` to leave; None: the socket's own linger) and
        wait until ZeroMQ has ended it, at most the linger and :data:`GRACE_S`. Returns whether it has (if
        not, a warning is logged: the buffers it was sending may still be in use)."""
        sock, ended = self.socket, self._ended
        _live.discard(self)
        if ended.closed:
            return True
        linger_ms = (sock.linger if not sock.closed else 0) if linger_s is None else round(linger_s * 1000)
        if not sock.closed:
            sock.close(linger_ms)
        wait_s = max(linger_ms, 0) / 1000 + GRACE_S
        done = bool(ended.poll(round(wait_s * 1000)))
        ended.close()
        if not done:
            log.warning("%s not ended by ZeroMQ %.1f s after its close: buffers it sent may still be in use",
                        sock, wait_s)
        return done


@atexit.register
def _close_all() -> None:
    """Before pyzmq frees what ZeroMQ still holds: close every guarded socket (its own linger) and wait."""
    for guard in list(_live):
        guard.close()
