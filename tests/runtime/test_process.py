"""What a node gets as a process (runtime/process.py): log lines on stderr and on the log topic, and
signals that end its loop."""

import logging
import os
import signal

import pytest
from polarstripe.msgs import Log
from polarstripe.nodes.demo import Talker
from polarstripe.runtime.process import install_logging, install_signals
from polarstripe.runtime.testing import MockBus


def _talker(**params):
    bus = MockBus()
    return Talker("talker", namespace="/rig", params=params, bus=bus), bus


def test_log_records_go_to_stderr_and_the_log_topic_uncounted(capfd):
    node, bus = _talker(log_level="INFO")
    install_logging(node, bus)
    node.log.debug("not at INFO")
    node.log.warning("careful %d", 3)
    node.log.log(logging.CRITICAL, "on fire")
    logs = bus.sent["/rig/log"]
    assert [(m.level, m.node, m.text) for m in logs] == [("WARNING", "talker", "careful 3"),
                                                        ("CRITICAL", "talker", "on fire")]
    assert all(isinstance(m, Log) for m in logs) and node.counters["published"] == 0
    err = capfd.readouterr().err.splitlines()
    assert len(err) == 2 and err[0].endswith("WARNING talker: careful 3")


def test_without_a_bus_only_stderr_and_a_failing_bus_never_breaks_logging(capfd):
    node, bus = _talker()
    install_logging(node)
    node.log.error("alone")
    assert "/rig/log" not in bus.sent and capfd.readouterr().err.endswith("ERROR talker: alone\n")

    class Broken(MockBus):
        def publisher(self, topic, msg_type):
            raise OSError("socket gone")

    install_logging(node, Broken())
    node.log.error("still here")  # the bus handler swallows its failure
    assert capfd.readouterr().err.endswith("ERROR talker: still here\n")


def test_sigterm_stops_the_loop_and_a_second_sigint_interrupts():
    node, _ = _talker()
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        install_signals(node)
        os.kill(os.getpid(), signal.SIGTERM)
        assert node.stopping and node.stop_reason == "SIGTERM"
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)  # already stopping: the second one is Ctrl-C for real
    finally:
        signal.signal(signal.SIGINT, handlers[0])
        signal.signal(signal.SIGTERM, handlers[1])
