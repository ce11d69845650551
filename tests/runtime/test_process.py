"""What a node gets as a process (runtime/process.py): log lines on stderr and on the log topic, and
signals that end its loop."""

import logging
import os
import signal

import pytest
from polarstripe.msgs import Log
from polarstripe.nodes.demo import Talker
from polarstripe.runtime.mock_bus import MockBus
from polarstripe.runtime.process import install_logging, install_signals


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


def _silent_service(tmp_path):
    """A ROUTER socket that takes requests and never answers (a peer stuck or gone)."""
    import zmq

    ctx = zmq.Context.instance()
    router = ctx.socket(zmq.ROUTER)
    router.linger = 0
    endpoint = f"ipc://{tmp_path}/silent.srv"
    router.bind(endpoint)
    return router, endpoint


def test_a_stop_signal_cuts_a_service_call_short_and_cleanup_calls_are_bounded(tmp_path):
    """While the node runs, SIGINT ends a long service call with NodeStopping (not a timeout); once it is
    stopping, a call (teardown putting the rig back) waits CLEANUP_CALL_S, not its own 30 s."""
    import threading

    from polarstripe.msgs import Ack, Empty
    from polarstripe.runtime.bus import ServiceTimeout
    from polarstripe.runtime.node import NodeStopping
    from polarstripe.runtime.process import CLEANUP_CALL_S, GuardedClient
    from polarstripe.runtime.service import ServiceClient

    router, endpoint = _silent_service(tmp_path)
    node, _ = _talker()
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        guard = install_signals(node)
        client = GuardedClient(ServiceClient(endpoint, "/rig/x", Empty, Ack, timeout_s=30.0), guard)
        threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT)).start()
        with pytest.raises(NodeStopping) as stopped:
            client.call(Empty())
        assert stopped.value.topic == "/rig/x" and stopped.value.reason == "SIGINT" and node.stopping
        with pytest.raises(ServiceTimeout, match=rf"no reply within {CLEANUP_CALL_S} s"):
            client.call(Empty())  # cleanup: bounded however long the client's own timeout
        with pytest.raises(NodeStopping, match="setup"), guard.interruptible("setup"):
            pass  # a blocking section entered while stopping ends at once
    finally:
        signal.signal(signal.SIGINT, handlers[0])
        signal.signal(signal.SIGTERM, handlers[1])
        router.close()


def test_a_stop_signal_ends_a_blocking_section_at_once():
    """setup (the planner plans there for seconds) is cut short by SIGTERM: NodeStopping naming it."""
    from polarstripe.runtime.node import NodeStopping

    node, _ = _talker()
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        guard = install_signals(node)
        with pytest.raises(NodeStopping) as stopped, guard.interruptible("setup"):
            os.kill(os.getpid(), signal.SIGTERM)
            raise AssertionError("the signal should have ended the section")
        assert (stopped.value.topic, stopped.value.reason) == ("setup", "SIGTERM")
    finally:
        signal.signal(signal.SIGINT, handlers[0])
        signal.signal(signal.SIGTERM, handlers[1])


def test_a_signal_while_the_node_module_is_imported_ends_it_and_is_remembered():
    """early_signals: a SIGTERM during the import raises KeyboardInterrupt (exit 130, no traceback from the
    command line); if that was swallowed, install_signals stops the node at once with the signal's name.
    The mask is as before afterwards (held for a node the launcher started)."""
    from polarstripe.runtime import process
    from polarstripe.runtime.process import early_signals

    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    before = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    try:
        with pytest.raises(KeyboardInterrupt), early_signals():
            os.kill(os.getpid(), signal.SIGTERM)
        assert process._EARLY == ["SIGTERM"]
        assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == before
        assert signal.getsignal(signal.SIGTERM) is handlers[1]  # the import's handler is gone
        node, _ = _talker()
        install_signals(node)  # the KeyboardInterrupt was "swallowed": the node stops all the same
        assert node.stopping and node.stop_reason == "SIGTERM"
    finally:
        process._EARLY.clear()
        signal.signal(signal.SIGINT, handlers[0])
        signal.signal(signal.SIGTERM, handlers[1])


def test_a_signal_that_an_extensions_import_turns_into_an_import_error_is_still_a_stop(tmp_path, monkeypatch):
    """A KeyboardInterrupt that lands in a C extension's module init comes back as "ImportError:
    initialization failed" (seen once in tests/launch/test_sigint.py): after an early stop signal the node's
    command still ends as a Ctrl-C (exit 130, no traceback), not as a broken import (exit 1)."""
    from polarstripe.runtime import process
    from polarstripe.runtime.runner import run_node

    (tmp_path / "ext_like.py").write_text(
        "import os, signal, time\n"
        "try:\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    time.sleep(1.0)\n"
        "except KeyboardInterrupt:\n"
        "    raise ImportError('initialization failed')\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        with pytest.raises(KeyboardInterrupt):
            run_node("ext_like:Anything", pub=f"ipc://{tmp_path}/p", srv=f"ipc://{tmp_path}/s")
        assert process._EARLY == ["SIGTERM"]
    finally:
        process._EARLY.clear()
        signal.signal(signal.SIGINT, handlers[0])
        signal.signal(signal.SIGTERM, handlers[1])



def test_a_stop_signal_inside_numbas_compiler_waits_for_the_compile_to_end():
    """A signal that would cut numba's compiler (or cache loader) short waits until its lock is given back,
    then acts as it would have: llvmlite's half-built objects print tracebacks at exit otherwise."""
    import numba
    import numba.core.event as ev
    from polarstripe.runtime.node import NodeStopping
    from polarstripe.runtime.process import interruptible, release_signals

    node, _ = _talker()
    inside = []  # the guard's depth as a later listener sees it when numba takes its lock

    class Probe(ev.Listener):
        def on_start(self, event):
            inside.append(guard.compiling)

        def on_end(self, event):
            pass

    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    probe = Probe()
    try:
        guard = install_signals(node)
        ev.register("numba:compiler_lock", probe)
        assert numba.njit(lambda x: x * 2)(3) == 6  # a real compile: the guard follows numba's lock
        assert inside and min(inside) >= 1 and guard.compiling == 0
        guard.compiler_lock(True)  # as numba's lock does: a signal now is held
        with interruptible("setup"):
            os.kill(os.getpid(), signal.SIGTERM)
            assert not node.stopping
            with pytest.raises(NodeStopping):
                guard.compiler_lock(False)  # given back: the held signal stops the node and cuts setup
        assert node.stopping and node.stop_reason == "SIGTERM" and guard.compiling == 0
    finally:
        ev.unregister("numba:compiler_lock", probe)
        release_signals()
        signal.signal(signal.SIGINT, handlers[0])
        signal.signal(signal.SIGTERM, handlers[1])


def test_a_signal_swallowed_by_a_finalizer_during_the_import_is_one_plain_line(capfd):
    """A stop signal during the import raises KeyboardInterrupt wherever Python is, a finalizer or an
    import's callback included: Python cannot raise it there and would print it with a traceback. The stop
    is remembered (the node stops once its handlers are in) and the note is one line."""
    import sys

    from polarstripe.runtime import process

    class Finalized:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(10_000):  # the handler runs here, inside the finalizer
                pass

    hook = sys.unraisablehook
    try:
        with process.early_signals():
            x = Finalized()
            del x
        assert process.early_signal_seen()
        err = capfd.readouterr().err
        assert "Traceback" not in err and "KeyboardInterrupt ignored in" in err, err
    finally:
        sys.unraisablehook = hook
        process._EARLY.clear()


def test_a_stop_signal_during_a_nodes_last_half_second_is_no_traceback():
    """``python -m polarstripe node``: after the node's loop has ended, __main__ gives the sockets' linger up
    to 0.5 s, then leaves. A stop signal then (the launcher's next one) has nothing left to stop; it raised
    KeyboardInterrupt there, a traceback in the node's log. Here main() returns at once and a SIGINT comes
    0.1 s into a linger made 0.4 s long: the exit is the node's own status, with nothing on stderr."""
    import subprocess
    import sys

    code = """
import os, runpy, signal, sys, threading, time
import zmq
import polarstripe.tools.cli as cli

class Slow:
    def destroy(self, linger=None):
        time.sleep(0.4)

def main():
    threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGINT)).start()
    return 3

zmq.Context.instance = staticmethod(lambda: Slow())
cli.main = main
sys.argv = ["polarstripe", "node"]
runpy.run_module("polarstripe", run_name="__main__")
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 3, done.stderr
    assert "Traceback" not in done.stderr and "KeyboardInterrupt" not in done.stderr, done.stderr
