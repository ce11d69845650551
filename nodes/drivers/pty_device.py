"""A fake serial device on a pseudo-terminal: the driver opens the slave path with real pyserial.

Subclasses implement :meth:`PtyDevice.feed` (bytes the host wrote; return nothing, answer with
:meth:`PtyDevice.reply`) and may implement :meth:`PtyDevice.poll` (called at least every ``poll_s``, for the
device's own timeouts). The device serves the pty master in a thread; ``start``/``stop`` or a context
manager.
"""

from __future__ import annotations

import os
import select
import threading
import tty


class PtyDevice:
    """Serve a pty master in a thread; :attr:`port` is the path the driver opens."""

    poll_s = 0.01

    def __init__(self):
        self.port: str | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._write_lock = threading.Lock()
        self.received = bytearray()  # everything the host wrote, for tests and debugging

    def start(self):
        self._master, self._slave = os.openpty()
        tty.setraw(self._master)
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._thread = threading.Thread(
            target=self._serve, name=f"{type(self).__name__} {self.port}", daemon=True
        )
        self._thread.start()
        return self

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], self.poll_s)
                data = os.read(self._master, 256) if ready else b""
            except OSError:
                return
            if data:
                self.received += data
                self.feed(data)
            self.poll()

    def feed(self, data: bytes) -> None:
        raise NotImplementedError

    def poll(self) -> None:
        """Called after every read and at least every ``poll_s`` seconds; a hook for timeouts."""

    def reply(self, data: bytes) -> None:
        """Write ``data`` to the host (thread-safe)."""
        with self._write_lock:
            if self._master is not None:
                os.write(self._master, data)

    def stop(self) -> None:
        """Stop serving and close the pty; idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
            self._thread = None
        with self._write_lock:
            for fd in (self._master, self._slave):
                if fd is not None:
                    os.close(fd)
            self._master = self._slave = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
