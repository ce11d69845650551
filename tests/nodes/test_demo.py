"""The demo nodes (nodes/demo.py) through the harness: the talker's counter, rate, reset and count; the
listener's count, report and stop."""

import pytest
from polarstripe.msgs import Empty, Log
from polarstripe.nodes.demo import Listener, Talker
from polarstripe.runtime.params import ParamError
from polarstripe.runtime.testing import NodeHarness


def test_talker_publishes_its_counter_at_its_rate():
    h = NodeHarness(Talker, namespace="/demo", params={"rate_hz": 20, "text": "hi"})
    assert h.advance(0.5) == ["tick"] * 10
    msgs = h.published("chatter")
    assert [m.text for m in msgs] == [f"hi {n}" for n in range(10)]
    assert {m.node for m in msgs} == {"talker"} and [m.header.seq for m in msgs] == list(range(10))


def test_talker_reset_is_private_to_the_node_and_restarts_the_counter():
    h = NodeHarness(Talker, name="t2", namespace="/demo", params={"rate_hz": 10})
    h.advance(0.35)
    assert h.full("~/reset") == "/demo/t2/reset"
    assert h.call("~/reset", Empty()).detail == "reset from 3"
    h.advance(0.1)
    assert h.published("chatter")[-1].text == "hello 0"


def test_talker_stops_after_count_with_the_reason():
    h = NodeHarness(Talker, params={"rate_hz": 100, "count": 4})
    h.advance(1.0)
    assert len(h.published("chatter")) == 4 and h.node.stop_reason == "sent 4 messages"


@pytest.mark.parametrize(("params", "text"), [({"rate_hz": 0}, "rate_hz must be > 0"),
                                              ({"count": -1}, "count must be >= 0")])
def test_talker_params_are_checked(params, text):
    with pytest.raises(ParamError, match=text):
        NodeHarness(Talker, params=params)


def test_listener_counts_every_message_reports_and_stops_after_count():
    h = NodeHarness(Listener, params={"count": 3, "report_s": 1.0})
    for text in ("a", "b"):
        h.queue("chatter", Log(level="INFO", node="t", text=text))
    h.advance(1.0)
    assert h.call("~/count", Empty()).detail == "2"
    assert ("INFO", "heard 2 messages, last 'b'") in h.logs
    h.deliver("chatter", Log(level="INFO", node="t", text="c"))
    assert h.node.stop_reason == "heard 3 messages"
    assert h.logs[-1] == ("INFO", "heard 3 messages in all (heard 3 messages)")  # its Stop event
