"""The harness (runtime/testing.py): the node's own loop over the mock bus, virtual time, and what each
harness call hands the loop."""

import time

import pytest
from polarstripe.msgs import Ack, Empty, Log, MessageError, PolarizerCommand
from polarstripe.runtime.bus import ServiceTimeout
from polarstripe.runtime.mock_bus import MockBus, Paused
from polarstripe.runtime.node import Node, Received, Stop, Tick
from polarstripe.runtime.node_bus import NodeBus
from polarstripe.runtime.testing import NodeHarness


class _Loop(Node):
    """A loop-style node that notes every event it sees (with the clock) and answers ~/seen."""

    SUBSCRIBES = {"a": Log, "b": PolarizerCommand}
    SERVES = {"~/seen": (Empty, Ack), "~/bad": (Empty, Ack), "~/odd": (Empty, Ack)}

    def setup(self):
        self.seen = []
        self.teardowns = 0
        self.subscribe("a", mode="all")
        self.subscribe("b", mode="all")
        self.serve("~/seen", lambda req: Ack(ok=True, detail=str(len(self.seen))))
        self.serve("~/bad", self.bad)
        self.serve("~/odd", lambda req: Empty())
        self.every(0.25, name="quarter")

    def bad(self, req):
        raise RuntimeError("handler failed")

    def run(self):
        for event in self.events():
            match event:
                case Received(topic=t, msg=m):
                    self.seen.append((t, getattr(m, "text", getattr(m, "target_deg", None)), self.now()))
                case Tick(timer=name, now_ns=ns):
                    self.seen.append(("tick", name, ns / 1e9))
                case Stop(reason=r):
                    self.seen.append(("stop", r, self.now()))

    def teardown(self):
        self.teardowns += 1


def _log(text):
    return Log(level="INFO", node="x", text=text)


def test_the_mock_bus_keeps_the_node_contract():
    assert isinstance(MockBus(), NodeBus)
    assert issubclass(Paused, BaseException) and not issubclass(Paused, Exception)


def test_advance_runs_the_nodes_own_loop_in_virtual_time():
    h = NodeHarness(_Loop)
    t0 = time.monotonic()
    assert h.advance(10.0) == ["quarter"] * 40
    assert time.monotonic() - t0 < 2.0 and h.bus.now() == 10.0
    ticks = [s for s in h.node.seen if s[0] == "tick"]
    assert [round(s[2], 9) for s in ticks[:3]] == [0.25, 0.5, 0.75]  # Tick.now_ns is the virtual clock


def test_advance_hands_over_queued_messages_in_order_deliver_only_its_own():
    h = NodeHarness(_Loop)
    h.queue("a", _log("q1"))
    h.queue("b", PolarizerCommand(target_deg=2.0))
    h.queue("a", _log("q2"))
    h.deliver("a", _log("now"))  # at once; the queued ones stay where they are
    assert [s[:2] for s in h.node.seen] == [("a", "now")]
    assert h.node.take("b") and h.node.take("b") == []  # Node.take finds what was queued
    h.advance(0.1)
    assert [s[:2] for s in h.node.seen] == [("a", "now"), ("a", "q1"), ("a", "q2")]
    assert all(s[2] == 0.0 for s in h.node.seen)  # arrived: no time passed


def test_queued_messages_of_several_topics_come_in_publication_order():
    h = NodeHarness(_Loop)
    h.queue("b", PolarizerCommand(target_deg=1.0))
    h.queue("a", _log("second"))
    h.advance(0.01)
    assert [s[:2] for s in h.node.seen] == [("b", 1.0), ("a", "second")]


def test_a_bad_message_goes_through_the_loops_bad_message_path():
    h = NodeHarness(_Loop)
    h.deliver_raw("a", [b"\xc1"])
    assert h.node.counters["bad"] == 1 and h.node.seen == []
    assert h.node._subs["a"].source.stats.bad == 1 and "topic '/a'" in h.logs[-1][1]


def test_calls_are_answered_by_the_loop_with_the_handlers_errors_raised_here():
    h = NodeHarness(_Loop, namespace="/rig")
    h.deliver("a", _log("x"))
    assert h.call("~/seen", Empty()).detail == "1"
    assert h.bus.handlers["/rig/_loop/seen"]  # the private name, in the node's namespace
    with pytest.raises(RuntimeError, match="handler failed"):
        h.call("~/bad", Empty())
    with pytest.raises(MessageError, match="handler returned Empty, expected 'ack'"):
        h.call("~/odd", Empty())
    assert h.call("~/seen", Empty()).ok  # the loop goes on after a failed handler


def test_stop_reaches_the_loop_once_and_teardown_runs_once():
    h = NodeHarness(_Loop)
    h.advance(0.3)
    h.stop("first")
    h.stop("second")
    assert [s for s in h.node.seen if s[0] == "stop"] == [("stop", "first", 0.3)]
    assert h.node.teardowns == 1
    assert h.advance(1.0) == [] and h.bus.now() == pytest.approx(1.3)  # a stopped node runs no more
    h.deliver("a", _log("late"))
    assert not [s for s in h.node.seen if s[0] == "a"]


def test_a_node_that_stops_itself_gets_its_stop_event_in_that_advance():
    class Three(_Loop):
        def run(self):
            for event in self.events():
                if isinstance(event, Tick) and len(self.seen) == 2:
                    self.stop("three ticks")
                self.seen.append(type(event).__name__)

    h = NodeHarness(Three)
    assert h.advance(5.0) == ["quarter"] * 3
    assert h.node.seen == ["Tick", "Tick", "Tick", "Stop"] and h.node.stop_reason == "three ticks"


def test_a_node_catching_every_exception_still_hands_control_back():
    class Stubborn(_Loop):
        def run(self):
            try:
                for _ in self.events():
                    pass
            except Exception:  # noqa: BLE001 - the point: Paused is not an Exception
                self.seen.append("swallowed")

    h = NodeHarness(Stubborn)
    h.advance(1.0)
    assert h.node.seen == [] and h.bus.now() == 1.0


def test_fake_peers_answer_calls_and_react_to_publications():
    class Caller(Node):
        PUBLISHES = {"cmd": PolarizerCommand}

        def setup(self):
            self.pub = self.publisher("cmd")
            self.client_ = self.client("peer/echo", Empty, Ack, timeout_s=3.0)

    h = NodeHarness(Caller)
    heard = []
    h.on_publish("cmd", lambda m: heard.append((m.target_deg, m.header.seq)))
    h.node.pub.publish(PolarizerCommand(target_deg=5.0))
    assert heard == [(5.0, 0)]
    with pytest.raises(ServiceTimeout, match="no responder"):
        h.node.client_.call(Empty())
    assert h.bus.now() == 3.0  # the timeout cost virtual time only
    h.on_call("peer/echo", lambda req: Ack(ok=True, detail="hi"))
    assert h.node.client_.call(Empty()).detail == "hi"
    assert [type(r) for r in h.bus.clients["/peer/echo"].requests] == [Empty, Empty]


def test_a_deferred_reply_is_waited_for_by_call_and_requests_wait_for_the_loop():
    from polarstripe.runtime.node_bus import Deferred

    class Later(Node):
        SERVES = {"work": (Empty, Ack), "now": (Empty, Ack)}

        def setup(self):
            self.waiting = []
            self.serve("work", self.work)
            self.serve("now", lambda req: Ack(ok=True, detail=str(len(self.waiting))))
            self.every(0.02, self.finish)

        def work(self, req):
            self.waiting.append((Deferred(), self.now()))
            return self.waiting[-1][0]

        def finish(self):  # a piece of work takes 0.05 s of the node's clock
            while self.waiting and self.now() - self.waiting[0][1] >= 0.05:
                self.waiting.pop(0)[0].reply(Ack(ok=True, detail=f"done at {self.now():.2f}"))

    h = NodeHarness(Later)
    t0 = time.monotonic()
    assert h.call("work", Empty()).detail == "done at 0.06"
    assert time.monotonic() - t0 >= 0.05  # virtual time kept in step with real time while waiting
    first, second = h.request("work", Empty()), h.request("now", Empty())
    assert not first.done and not second.done  # nothing runs until the loop does
    h.advance(0.01)
    assert second.result().detail == "1" and not first.done
    with pytest.raises(ServiceTimeout, match="not answered"):
        first.result()
    h.advance(0.1)
    assert first.result().detail == "done at 0.12"
