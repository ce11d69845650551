"""The demo nodes (nodes/demo.py) on the NodeHarness: the talker's counter, its private reset service, its
params' checks, the listener's count, report and stop, and the two wired together. (tests/runtime/test_node.py
uses them to exercise the runtime; this checks their own behaviour.)"""

from __future__ import annotations

import pytest
from polarstripe.msgs import Ack, Empty, Log
from polarstripe.nodes.demo import Listener, Talker
from polarstripe.runtime.node import Received, Tick
from polarstripe.runtime.params import ParamError
from polarstripe.runtime.testing import NodeHarness


def _texts(h: NodeHarness) -> list[str]:
    return [m.text for m in h.published("chatter")]


def test_talker_counts_at_its_rate_and_never_stops_with_count_zero():
    h = NodeHarness(Talker, namespace="/demo", params={"rate_hz": 20})
    h.advance(50.0)
    sent = h.published("/demo/chatter")
    assert len(sent) == 1000
    assert sent[0].text == "hello 0" and sent[-1].text == "hello 999"
    assert [m.header.seq for m in sent] == list(range(1000))
    assert all(m.level == "INFO" and m.node == "talker" for m in sent)
    assert not h.node.stopping


def test_talker_reset_restarts_the_count_and_says_from_where():
    h = NodeHarness(Talker, name="t2", namespace="/demo", params={"rate_hz": 10, "text": "n"})
    h.advance(0.45)
    assert _texts(h) == ["n 0", "n 1", "n 2", "n 3"]
    assert "/demo/t2/reset" in h.bus.handlers  # private: <namespace>/<node name>/reset
    reply = h.call("~/reset", Empty())
    assert type(reply) is Ack and reply.ok and reply.detail == "reset from 4"
    h.advance(0.1)
    assert _texts(h)[-1] == "n 0"
    assert h.call("/demo/t2/reset", Empty()).detail == "reset from 1"


def test_talker_stops_after_count_with_the_reason():
    h = NodeHarness(Talker, params={"rate_hz": 100, "count": 5})
    h.advance(10.0)
    assert len(_texts(h)) == 5
    assert h.node.stopping and h.node.stop_reason == "sent 5 messages"


@pytest.mark.parametrize(
    "params, match",
    [
        ({"rate_hz": 0}, "rate_hz must be > 0, got 0.0"),
        ({"rate_hz": "-2"}, "rate_hz must be > 0, got -2.0"),
        ({"count": -1}, "count must be >= 0, got -1"),
        ({"rate": 5}, "unknown param 'rate'"),
    ],
)
def test_talker_params_are_checked(params, match):
    with pytest.raises(ParamError, match=match):
        NodeHarness(Talker, params=params)


def test_listener_counts_reports_and_serves_its_count():
    h = NodeHarness(Listener, namespace="/demo", params={"report_s": 2.0})
    for text in ("a", "b", "c"):
        h.deliver("chatter", Log(level="INFO", node="talker", text=text))
    assert (h.node.heard, h.node.last) == (3, "c")
    reply = h.call("~/count", Empty())
    assert (reply.ok, reply.detail) == (True, "3")
    assert h.advance(4.5) == ["report", "report"]
    assert h.logs.count(("INFO", "heard 3 messages, last 'c'")) == 2
    h.stop("done")
    assert h.logs[-1] == ("INFO", "heard 3 messages in all (done)")


def test_listener_stops_after_count_and_hears_no_more():
    h = NodeHarness(Listener, params={"count": 2})
    h.feed([Tick("report", 0)] + [_received(f"m{i}") for i in range(4)])
    assert h.node.heard == 2 and h.node.last == "m1"
    assert h.node.stopping and h.node.stop_reason == "heard 2 messages"


def _received(text: str) -> Received:
    return Received("chatter", Log(level="INFO", node="t", text=text))


def test_talker_feeds_listener_through_the_codec():
    talker = NodeHarness(Talker, namespace="/demo", params={"rate_hz": 50, "count": 25, "text": "ping"})
    talker.advance(1.0)
    listener = NodeHarness(Listener, namespace="/demo", params={"count": 0})
    for msg in talker.published("chatter"):
        listener.deliver("chatter", msg)
    assert listener.node.heard == 25 and listener.node.last == "ping 24"
    assert listener.call("~/count", Empty()).detail == "25"


def test_declared_interfaces_are_the_ones_a_launch_graph_shows():
    assert Talker.PUBLISHES == {"chatter": Log} and Talker.SERVES == {"~/reset": (Empty, Ack)}
    assert Listener.SUBSCRIBES == {"chatter": Log} and Listener.SERVES == {"~/count": (Empty, Ack)}
    t, li = NodeHarness(Talker, namespace="/demo"), NodeHarness(Listener, namespace="/demo")
    assert t.full("chatter") == li.full("chatter") == "/demo/chatter"
    assert li.bus.sources["/demo/chatter"].mode == "all"  # every message counted, none skipped
