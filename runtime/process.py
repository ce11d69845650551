"""What a node needs when it runs as a process (:func:`polarstripe.runtime.runner.run_node`): log lines on
stderr and on the namespace's ``log`` topic, and SIGINT/SIGTERM ending it in time (docs/architecture.md
"Shutdown").

A stop signal ends the node's loop (:meth:`Node.stop`); the loop's own waits look at it every
``STOP_CHECK_S``. What does not return to the loop by itself is cut short: while ``setup`` runs or a service
call waits for its reply (:class:`GuardedClient`), the signal raises :class:`NodeStopping` at once. A service
call made while the node is already stopping (a ``teardown`` putting the rig back) waits at most
:data:`CLEANUP_CALL_S`, so cleanup never holds a shutdown beyond a short bound. While numba compiles or
loads a cached kernel (its compiler lock held), a stop signal waits for the lock to be given back."""

from __future__ import annotations

import logging
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager

from polarstripe.msgs import Log
from polarstripe.runtime.node import Node, NodeStopping
from polarstripe.runtime.node_bus import NodeBus

CLEANUP_CALL_S = 0.5
"""The longest a service call made by a stopping node (its cleanup) waits for a reply [s]."""


class BusLogHandler(logging.Handler):
    """Publishes log records as :class:`~polarstripe.msgs.Log` on the namespace's ``log`` topic (straight on
    the bus: log messages are not counted as the node's ``published``)."""

    def __init__(self, node: Node, bus: NodeBus):
        super().__init__()
        self._node, self._bus = node, bus
        self._pub = None
        self._busy = False

    def emit(self, record: logging.LogRecord) -> None:
        if self._busy:
            return
        self._busy = True
        try:
            if self._pub is None:
                self._pub = self._bus.publisher(self._node.resolve("log"), Log)
            level = (
                record.levelname if record.levelname in ("DEBUG", "INFO", "WARNING", "ERROR") else "CRITICAL"
            )
            self._pub.publish(Log(level=level, node=self._node.name, text=record.getMessage()))
        except Exception:  # logging must never take the node down
            pass
        finally:
            self._busy = False


def install_logging(node: Node, bus: NodeBus | None = None) -> None:
    """stderr lines ``time LEVEL node: text`` and, given the node's ``bus``, the ``log`` topic."""
    log = node.log
    log.setLevel(node.params.log_level)
    log.propagate = False
    for h in list(log.handlers):
        log.removeHandler(h)
    err = logging.StreamHandler(sys.stderr)
    err.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(nodename)s: %(message)s"))
    err.addFilter(lambda r: setattr(r, "nodename", node.name) or True)
    log.addHandler(err)
    if bus is not None:
        log.addHandler(BusLogHandler(node, bus))


class StopGuard:
    """SIGINT and SIGTERM for one node: :meth:`Node.stop` with the signal's name; inside
    :meth:`interruptible` (``setup``, a service call) also :class:`NodeStopping` raised at once. A second
    SIGINT while stopping raises ``KeyboardInterrupt`` (the runner exits 130)."""

    def __init__(self, node: Node):
        self.node = node
        self._waiting: list[str] = []  # what the node is blocked in, innermost last
        self.compiling = 0  # depth of numba's compiler lock (compiling or loading a cached kernel)
        self._deferred: int | None = None  # a stop signal that came while compiling

    def compiler_lock(self, held: bool) -> None:
        """numba's compiler lock taken (``held``) or given back: a stop signal that came while it was held
        acts now. Cut short inside numba's compiler or cache loader, llvmlite leaves half-built objects
        whose finalizers print tracebacks at exit; a compile or a cache load takes a few seconds at most."""
        self.compiling += 1 if held else -1
        if not self.compiling and self._deferred is not None:
            signum, self._deferred = self._deferred, None
            self.on_signal(signum, None)

    @contextmanager
    def interruptible(self, what: str) -> Iterator[None]:
        """A blocking section that a stop signal cuts short (``NodeStopping`` naming ``what``)."""
        if self.node.stopping:
            raise NodeStopping(self.node.name, what, self.node.stop_reason)
        self._waiting.append(what)
        try:
            yield
        finally:
            self._waiting.pop()

    def on_signal(self, signum, frame) -> None:
        if self.compiling:
            self._deferred = signum
            return
        name = signal.Signals(signum).name
        if self.node.stopping and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.node.stop(name)
        if self._waiting:
            raise NodeStopping(self.node.name, self._waiting[-1], name)


class GuardedClient:
    """A node's service client when it runs as a process (wraps a
    :class:`~polarstripe.runtime.service.ServiceClient`; everything but :meth:`call` passes through).

    A call while the node runs waits as asked but ends with :class:`NodeStopping` as soon as SIGINT/SIGTERM
    comes; a call while the node stops (cleanup) waits at most :data:`CLEANUP_CALL_S`."""

    def __init__(self, client, guard: StopGuard):
        self._client, self._guard = client, guard

    def call(self, request, timeout_s: float | None = None, *, check=None):
        if self._guard.node.stopping:
            wait = self._client.timeout_s if timeout_s is None else timeout_s
            return self._client.call(request, min(wait, CLEANUP_CALL_S), check=check)
        try:
            with self._guard.interruptible(self._client.name):
                return self._client.call(request, timeout_s, check=check)
        except NodeStopping:
            self._client.close()  # the request may be queued or half answered: a fresh socket next time
            raise

    def __getattr__(self, name: str):
        return getattr(self._client, name)


_GUARD: StopGuard | None = None  # this process's node, once install_signals has run
_LOCK_LISTENER = None  # the numba event listener telling _GUARD about numba's compiler lock


@contextmanager
def interruptible(what: str) -> Iterator[None]:
    """Around a node's long computation that may be abandoned midway (no socket or file half written: the
    planner's re-plan): a stop signal ends it at once with :class:`NodeStopping`, which ends the node
    normally. A no-op where no signals are installed (the harness, a script)."""
    if _GUARD is None:
        yield
        return
    with _GUARD.interruptible(what):
        yield


_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_EARLY: list[str] = []  # stop signals that came while the node's module was imported
_BEFORE: dict = {}  # the handlers install_signals replaced


def early_signal_seen() -> bool:
    """Whether a stop signal came while the node's module was imported (:func:`early_signals`)."""
    return bool(_EARLY)


@contextmanager
def early_signals() -> Iterator[None]:
    """Around importing a node's module (seconds of numba, scipy, OpenCV on a loaded machine): a stop signal
    ends the import at once with ``KeyboardInterrupt`` (the command exits 130) and is remembered, so that
    one swallowed by an import callback still stops the node in :func:`install_signals`. Afterwards the
    signals are held again (if they were: the launcher's node) until the node's own handlers are in."""
    def on_signal(signum, frame):
        _EARLY.append(signal.Signals(signum).name)
        sys.unraisablehook = _quiet_after_interrupt  # stays: the process stops, half-built objects die
        raise KeyboardInterrupt

    old = {s: signal.signal(s, on_signal) for s in _STOP_SIGNALS}
    mask = signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)  # one pending since the start comes now
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # held again if the launcher had them held
        for s, h in old.items():
            signal.signal(s, h)


def _quiet_after_interrupt(unraisable) -> None:
    """``sys.unraisablehook`` once an import was cut short: Python prints, with a traceback, what it cannot
    raise (our ``KeyboardInterrupt`` swallowed by an import's callback; a finalizer of an object whose
    constructor was interrupted, e.g. llvmlite's). Here the stop is already remembered: one plain line."""
    print(f"stopping during the import: {type(unraisable.exc_value).__name__} ignored in "
          f"{getattr(unraisable.object, '__qualname__', type(unraisable.object).__name__)}", file=sys.stderr)


def install_signals(node: Node) -> StopGuard:
    """SIGINT and SIGTERM stop the node (see :class:`StopGuard`); returns the guard."""
    global _GUARD
    guard = _GUARD = StopGuard(node)
    _BEFORE.update({s: signal.getsignal(s) for s in _STOP_SIGNALS})
    signal.signal(signal.SIGINT, guard.on_signal)
    signal.signal(signal.SIGTERM, guard.on_signal)
    _watch_compiler_lock(guard)
    if _EARLY:  # one came during the import and its KeyboardInterrupt was lost: stop as it asked
        node.stop(_EARLY[0])
    # the launcher starts nodes with both blocked (runtime/launch.py): one that came meanwhile arrives now
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)
    return guard


def release_signals() -> None:
    """Undo :func:`install_signals` once the node has ended: a node run inside a longer process (a test, a
    script) leaves no guard behind that would cut the next node's computation short."""
    global _GUARD, _LOCK_LISTENER
    _GUARD = None
    if _LOCK_LISTENER is not None:
        sys.modules["numba.core.event"].unregister("numba:compiler_lock", _LOCK_LISTENER)
        _LOCK_LISTENER = None
    for s, h in _BEFORE.items():
        signal.signal(s, h)
    _BEFORE.clear()


def _watch_compiler_lock(guard: StopGuard) -> None:
    """Tell ``guard`` when numba's compiler lock is taken and given back (:meth:`StopGuard.compiler_lock`),
    if the node's module imported numba (none that does not pays for importing it)."""
    global _LOCK_LISTENER
    ev = sys.modules.get("numba.core.event")
    if ev is None:
        return

    class CompilerLockListener(ev.Listener):
        def on_start(self, event):
            guard.compiler_lock(True)

        def on_end(self, event):
            guard.compiler_lock(False)

    _LOCK_LISTENER = CompilerLockListener()
    ev.register("numba:compiler_lock", _LOCK_LISTENER)
