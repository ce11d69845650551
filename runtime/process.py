"""What a node needs when it runs as a process (:func:`polarstripe.runtime.runner.run_node`): log lines on
stderr and on the namespace's ``log`` topic, and SIGINT/SIGTERM ending its loop."""

from __future__ import annotations

import logging
import signal
import sys

from polarstripe.msgs import Log
from polarstripe.runtime.node import Node
from polarstripe.runtime.node_bus import NodeBus


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


def install_signals(node: Node) -> None:
    """SIGINT and SIGTERM stop the node's loop (the second SIGINT raises KeyboardInterrupt)."""

    def on_signal(signum, frame):
        name = signal.Signals(signum).name
        if node.stopping and signum == signal.SIGINT:
            raise KeyboardInterrupt
        node.stop(name)

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
