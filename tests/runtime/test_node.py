from typing import Literal

import numpy as np
import pytest
from polarstripe.msgs import Ack, Empty, Frame, Log, PolarizerState, ScanEvent, ScanRequest, encode
from polarstripe.nodes.demo import Listener, Talker
from polarstripe.runtime.bus import BusTimeout, ServiceTimeout
from polarstripe.runtime.node import Node, NodeError, NodeStopping, Received, Stop, Tick
from polarstripe.runtime.params import NodeParams
from polarstripe.runtime.testing import NodeHarness


class _Scanner(Node):
    class Params(NodeParams):
        mode: Literal["flood", "stripes"] = "flood"
        angles: list[float] = [0.0, 90.0]
        limit: int | None = None

    PUBLISHES = {"emitter/scan": ScanEvent}
    SUBSCRIBES = {"polarizer/state": PolarizerState, "camera/frame": Frame}
    SERVES = {"emitter/start_scan": (ScanRequest, ScanEvent)}

    def setup(self):
        self.scan = self.publisher("emitter/scan")
        self.subscribe("polarizer/state", mode="latest")
        self.subscribe("camera/frame", self.on_frame, mode="all")
        self.serve("emitter/start_scan", self.start)
        self.frames = []

    def on_frame(self, msg):
        assert not msg.image.flags.writeable
        self.frames.append(msg.step)

    def start(self, req):
        settled = self.wait_for("polarizer/state", lambda m: m.settled, timeout_s=1.0)
        ev = ScanEvent(scan_id=7, event="start", method=req.method, analyzer_deg=[settled.angle_deg])
        self.scan.publish(ev)
        return ev


def test_talker_timer_publishes_through_the_codec_and_stops_after_count():
    h = NodeHarness(Talker, namespace="/rig", params={"rate_hz": "4", "count": 3, "text": "hey"})
    assert h.advance(0.6) == ["tick", "tick"]  # at 0.25 s and 0.5 s
    h.advance(10)
    assert [m.text for m in h.published("chatter")] == ["hey 0", "hey 1", "hey 2"]
    assert [m.header.seq for m in h.published("/rig/chatter")] == [0, 1, 2]
    assert h.node.stopping and h.node.counters["published"] == 3


def test_services_and_loop_style_node():
    talker = NodeHarness(Talker)
    talker.advance(0.35)
    assert talker.call("~/reset", Empty()).detail == "reset from 3"
    listener = NodeHarness(Listener, params={"count": 2})
    listener.deliver("chatter", Log(level="INFO", node="t", text="a"))
    reply = listener.call("~/count", Empty())
    assert type(reply) is Ack and reply.ok and reply.detail == "1"
    listener.feed(
        [
            Tick("report", 0),
            Received("chatter", Log(level="INFO", node="t", text="b")),
            Received("chatter", Log(level="INFO", node="t", text="c")),
        ]
    )
    assert listener.node.heard == 2 and listener.node.stopping  # stopped at 2: "c" never delivered
    assert ("INFO", "heard 1 messages, last 'a'") in listener.logs


def test_bad_message_is_logged_once_counted_dropped_and_the_node_keeps_going():
    h = NodeHarness(_Scanner)
    good = Frame(image=np.zeros((2, 2), np.uint16), exposure_s=0.1, step=1)
    h.deliver("camera/frame", good)
    h.deliver_raw("camera/frame", [b"\xc1junk"])
    h.deliver_raw("camera/frame", encode(Log(level="INFO", node="x", text="wrong type")))
    h.deliver("camera/frame", Frame(image=np.zeros((2, 2), np.uint16), exposure_s=0.1, step=2))
    assert h.node.frames == [1, 2]
    assert h.node.counters["bad"] == 2
    warnings = [t for lvl, t in h.logs if lvl == "WARNING"]
    assert len(warnings) == 2
    assert "topic '/camera/frame': field 'header'" in warnings[0]
    assert "field 'type': expected 'frame', got 'log'" in warnings[1]


def test_bad_message_logging_is_rate_limited():
    h = NodeHarness(_Scanner)
    for _ in range(250):
        h.deliver_raw("camera/frame", [b"\xc1"])
    assert h.node.counters["bad"] == 250
    assert len(h.logs) == 5 + 2  # the first five, then the 100th and the 200th


def test_wait_for_inside_a_service_handler_and_its_timeout():
    h = NodeHarness(_Scanner, namespace="/rig")
    h.queue("polarizer/state", PolarizerState(angle_deg=10.0, target_deg=45.0, settled=False))
    h.queue("polarizer/state", PolarizerState(angle_deg=45.0, target_deg=45.0, settled=True))
    ev = h.call("emitter/start_scan", ScanRequest(method="stripes"))
    assert ev.analyzer_deg == [45.0] and h.published("emitter/scan")[0].scan_id == 7
    with pytest.raises(BusTimeout, match="no matching message on '/rig/polarizer/state' within 1.0 s"):
        h.call("emitter/start_scan", ScanRequest(method="stripes"))


def test_client_calls_are_answered_by_the_harness_or_time_out():
    class Caller(Node):
        def setup(self):
            self.c = self.client("emitter/start_scan", ScanRequest, ScanEvent, timeout_s=0.5)

    h = NodeHarness(Caller, namespace="/rig")
    with pytest.raises(ServiceTimeout):
        h.node.c.call(ScanRequest(method="flood"))
    h.on_call("emitter/start_scan", lambda r: ScanEvent(scan_id=1, event="start", method=r.method))
    assert h.node.c.call(ScanRequest(method="flood")).method == "flood"


def test_undeclared_interfaces_are_refused():
    class Bare(Node):
        pass

    h = NodeHarness(Bare)
    with pytest.raises(NodeError, match="'nope' is not in PUBLISHES"):
        h.node.publisher("nope")
    with pytest.raises(NodeError, match="'nope' is not in SUBSCRIBES"):
        h.node.subscribe("nope")
    with pytest.raises(NodeError, match="service 'nope' is not in SERVES"):
        h.node.serve("nope", lambda r: r)
    h.node.publisher("dynamic", Log).publish(Log(level="INFO", node="b", text="ok"))  # explicit type: fine
    with pytest.raises(NodeError, match="period must be > 0"):
        h.node.every(0, lambda: None)


def test_names_resolve_in_the_namespace():
    h = NodeHarness(Talker, namespace="/rig/")
    assert h.full("chatter") == "/rig/chatter" and h.full("/abs/x") == "/abs/x"
    assert NodeHarness(Talker).full("chatter") == "/chatter"


def test_stop_event_reaches_a_loop_style_node():
    h = NodeHarness(Listener)
    h.stop()
    assert h.logs[-1] == ("INFO", "heard 0 messages in all (harness)")
    assert isinstance(Stop("x"), Stop)


def test_real_loop_delivers_messages_of_several_topics_in_publication_order(tmp_path):
    import time

    from polarstripe.msgs import Log, PolarizerCommand
    from polarstripe.runtime.bus import PubSocket
    from polarstripe.runtime.runner import ZmqNodeBus

    class Two(Node):
        SUBSCRIBES = {"first": Log, "second": PolarizerCommand}

        def setup(self):
            self.subscribe("first", mode="all")
            self.subscribe("second", mode="all")

    with PubSocket(f"ipc://{tmp_path}/src.pub") as src:
        bus = ZmqNodeBus(
            "two", pub=f"ipc://{tmp_path}/two.pub", srv=f"ipc://{tmp_path}/two.srv", connect=[src.endpoint]
        )
        node = Two("two", bus=bus)
        node.setup()
        first, second = src.publisher("/first", Log), src.publisher("/second", PolarizerCommand)
        deadline = time.monotonic() + 5
        while not all(s.source.socket.poll(0) for s in node._subs.values()):  # slow joiner
            assert time.monotonic() < deadline
            first.publish(Log(level="INFO", node="x", text="join"))
            second.publish(PolarizerCommand(target_deg=-1.0))
            time.sleep(0.02)
        for s in node._subs.values():
            s.source.take()
        second.publish(PolarizerCommand(target_deg=1.0), stamp_ns=100)  # published first ...
        first.publish(
            Log(level="INFO", node="x", text="later"), stamp_ns=200
        )  # ... though "first" polls first
        time.sleep(0.1)
        events = node.events()
        got = [next(events), next(events)]
        node.stop("done")
        assert [(e.topic, e.msg.header.stamp_ns) for e in got] == [("second", 100), ("first", 200)]
        assert isinstance(next(events), Stop)
        bus.close()


def test_real_wait_for_keeps_the_messages_after_its_match(tmp_path):
    import time

    from polarstripe.msgs import PolarizerCommand
    from polarstripe.runtime.bus import PubSocket
    from polarstripe.runtime.runner import ZmqNodeBus

    class Waiter(Node):
        SUBSCRIBES = {"cmd": PolarizerCommand}

        def setup(self):
            self.subscribe("cmd", mode="all")

    with PubSocket(f"ipc://{tmp_path}/src.pub") as src:
        bus = ZmqNodeBus(
            "w", pub=f"ipc://{tmp_path}/w.pub", srv=f"ipc://{tmp_path}/w.srv", connect=[src.endpoint]
        )
        node = Waiter("w", bus=bus)
        node.setup()
        cmd = src.publisher("/cmd", PolarizerCommand)
        sub = node._subs["cmd"].source
        deadline = time.monotonic() + 5
        while not sub.socket.poll(0):  # slow joiner
            assert time.monotonic() < deadline
            cmd.publish(PolarizerCommand(target_deg=-1.0))
            time.sleep(0.02)
        sub.take()
        for deg in (1.0, 2.0, 3.0, 4.0):  # all queued before the first wait_for
            cmd.publish(PolarizerCommand(target_deg=deg))
        time.sleep(0.1)
        got = [node.wait_for("cmd", lambda m: m.target_deg >= 2.0, timeout_s=2.0).target_deg]
        got += [node.wait_for("cmd", timeout_s=2.0).target_deg for _ in range(2)]
        assert got == [2.0, 3.0, 4.0]
        bus.close()


def test_wait_for_on_a_stopping_node_raises_node_stopping_not_a_timeout():
    h = NodeHarness(_Scanner, namespace="/rig")
    h.queue("polarizer/state", PolarizerState(angle_deg=45.0, target_deg=45.0, settled=True))
    h.node.stop("SIGTERM")
    stopping = r"/rig/polarizer/state.: the node is stopping \(SIGTERM\)"
    with pytest.raises(NodeStopping, match=stopping) as info:
        h.node.wait_for("polarizer/state", timeout_s=5.0)
    assert not isinstance(info.value, TimeoutError) and info.value.reason == "SIGTERM"
    assert h.bus.now() == 0.0  # raised at once, without waiting out the timeout


def test_real_wait_for_returns_promptly_when_stopped_from_elsewhere(tmp_path):
    import threading
    import time

    from polarstripe.msgs import PolarizerCommand
    from polarstripe.runtime.runner import ZmqNodeBus

    class Waiter(Node):
        SUBSCRIBES = {"cmd": PolarizerCommand}

        def setup(self):
            self.subscribe("cmd", mode="all")

    bus = ZmqNodeBus("w", pub=f"ipc://{tmp_path}/w.pub", srv=f"ipc://{tmp_path}/w.srv")
    node = Waiter("w", bus=bus)
    node.setup()
    timer = threading.Timer(0.2, node.stop, args=("told to",))
    timer.start()
    t0 = time.monotonic()
    try:
        with pytest.raises(NodeStopping, match=r"stopping \(told to\)"):
            node.wait_for("cmd", timeout_s=30.0)
        waited = time.monotonic() - t0
    finally:
        timer.cancel()
        bus.close()
    assert 0.2 <= waited < 0.2 + 0.2, waited


_WAITER = """
from polarstripe.msgs import PolarizerCommand
from polarstripe.runtime.node import Node


class Waiter(Node):
    SUBSCRIBES = {"cmd": PolarizerCommand}

    def setup(self):
        self.subscribe("cmd", mode="all")
        self.every(0.01, self.block)

    def block(self):
        self.log.info("waiting")
        self.wait_for("cmd", timeout_s=60.0)  # nothing ever comes; NodeStopping ends the node
"""


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_ends_a_node_blocked_in_wait_for_at_once_and_cleanly(tmp_path, sig):
    import os
    import signal
    import subprocess
    import sys
    import time

    (tmp_path / "waiter_mod.py").write_text(_WAITER)
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    log = tmp_path / "waiter.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "polarstripe", "node", "waiter_mod:Waiter", "--param", "heartbeat_s=0",
             "--pub", f"ipc://{tmp_path}/w.pub", "--srv", f"ipc://{tmp_path}/w.srv"],
            stdout=out, stderr=subprocess.STDOUT, env=env, cwd=tmp_path,
        )
    try:
        deadline = time.monotonic() + 30
        while "waiting" not in log.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.02)
        time.sleep(0.1)  # inside the zmq poll of wait_for
        t0 = time.monotonic()
        proc.send_signal(getattr(signal, sig))
        code = proc.wait(timeout=10)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log.read_text()
    assert code == 0 and "Traceback" not in text, text
    assert f"waiter: stopped ({sig})" in text, text
    assert took < 0.5, took  # the interpreter's exit included; not the 60 s timeout
