"""The sequencer's waits under the liveness watch (runtime/liveness.py), through the node harness (virtual
clock): a peer lost mid-scan is named at once; a respawned one gets the scan retried once, and it says so."""

import numpy as np
from polarstripe.msgs import Composite, Heartbeat, ScanEvent
from polarstripe.nodes.sequencer import Sequencer
from polarstripe.runtime.bus import RECONNECT_MAX_S
from polarstripe.runtime.testing import NodeHarness


def beat(node, inc=0, pid=10):
    return Heartbeat(node=node, pid=pid + inc, uptime_s=1.0,
                     counters={"incarnation": inc, "heartbeat_ms": 250})


def rig(graph, on_start, **params):
    h = NodeHarness(Sequencer, name="sequencer", namespace="/rig",
                    params={"methods": ["flood"], "plan": False, **params})
    h.bus.graph = {"nodes": {"sequencer": {}, **graph}}
    for name in graph:
        h.queue("heartbeat", beat(name))
    h.starts = []

    def start(req):
        sid = len(h.starts) + 1
        h.starts.append(sid)
        on_start(h, sid)
        return ScanEvent(scan_id=sid, event="start", method=req.method)

    h.on_call("emitter/start_scan", start)
    return h


def finish(h, sid):
    h.queue("emitter/scan", ScanEvent(scan_id=sid, event="done", method="flood"))
    h.queue("compositor/composite", Composite(images={"c": np.zeros((2, 2))}, method="flood", scan_id=sid,
                                              metrics={"contrast": 0.5}))


def test_an_emitter_that_stops_beating_mid_scan_is_named_and_ends_the_sequence():
    h = rig({"emitter": {"respawn": False}}, lambda h, sid: None, scan_timeout_s=600.0)
    h.node.run()
    assert h.node.exit_code == 1 and h.starts == [1]
    errors = [t for lvl, t in h.logs if lvl == "ERROR"]
    assert any(t.startswith("flood: scan 1: node 'emitter' lost: no heartbeat for 1.0") for t in errors)
    assert any("node 'emitter' lost and the launch does not respawn it" in t for t in errors), errors
    assert h.bus.clock < 5.0  # not the 600 s scan timeout (virtual clock)
    assert h.node.results["flood"]["event"] == "peer_lost"


def test_a_respawned_emitter_gets_the_scan_retried_once_with_a_new_scan_id():
    at = []

    def on_start(h, sid):
        at.append(h.bus.clock)
        if sid == 1:  # the emitter dies and comes back as incarnation 1: its beat shows it
            h.queue("heartbeat", beat("emitter", inc=1))
        else:
            finish(h, sid)

    h = rig({"emitter": {"respawn": True}}, on_start)
    h.node.run()
    assert h.node.exit_code == 0 and h.starts == [1, 2]
    # the retry waits until the compositor's subscription has found the new emitter (runtime/bus.py)
    assert at[1] - at[0] >= h.node.params.rejoin_s >= RECONNECT_MAX_S
    texts = [t for _, t in h.logs]
    assert any("node 'emitter' lost: respawned (incarnation 0 -> 1" in t for t in texts), texts
    assert any("flood: retrying the scan once: node 'emitter' is back (incarnation 1)" in t for t in texts)
    assert any("flood: scan 2 done" in t for t in texts)


def test_a_lost_grabber_that_comes_back_waits_for_the_old_scan_to_end_then_retries():
    def on_start(h, sid):
        if sid == 1:
            h.queue("heartbeat", beat("grabber", inc=1))
            h.queue("emitter/scan", ScanEvent(scan_id=1, event="fault", method="flood", detail="trigger"))
        else:
            finish(h, sid)

    h = rig({"grabber": {"respawn": True}}, on_start, respawn_wait_s=5.0)
    h.node.run()
    assert h.node.exit_code == 0 and h.starts == [1, 2]
    assert any("retrying the scan once: node 'grabber'" in t for _, t in h.logs)


def test_a_retry_is_made_once_only():
    def on_start(h, sid):
        h.queue("heartbeat", beat("emitter", inc=sid))  # every scan: the emitter dies again

    h = rig({"emitter": {"respawn": True}}, on_start)
    h.node.run()
    assert h.node.exit_code == 1 and h.starts == [1, 2]
    assert any("flood: scan 2 (retried for 'emitter'): node 'emitter' lost: respawned" in t
               for lvl, t in h.logs if lvl == "ERROR")


def test_a_peer_not_back_within_the_wait_ends_the_sequence():
    h = rig({"simulator": {"respawn": True}}, lambda h, sid: None, respawn_wait_s=3.0)
    h.node.run()
    assert h.node.exit_code == 1 and h.starts == [1]
    assert any("node 'simulator' lost and not back within 3 s" in t for _, t in h.logs)


def test_a_polarized_scan_also_depends_on_the_polarizer_and_only_nodes_of_the_graph_count():
    h = rig({"polarizer": {}, "emitter": {}}, lambda h, sid: None)
    assert h.node.scan_peers("flood") == ["emitter"]
    assert h.node.scan_peers("polarized_flood") == ["emitter", "polarizer"]


def test_a_fault_that_comes_before_the_dead_peers_deadline_is_still_laid_at_its_door():
    """The simulator dies; the polarizer notices its drive's silence first and the scan faults 0.5 s later:
    the sequencer waits for every peer to beat once more (or be lost) before it calls it a plain fault."""
    def on_start(h, sid):
        h.queue("emitter/scan", ScanEvent(scan_id=sid, event="fault", method="flood",
                                          detail="polarizer/state"))

    h = rig({"simulator": {"respawn": False}}, on_start)
    h.node.run()
    assert h.node.exit_code == 1 and h.starts == [1]
    errors = [t for lvl, t in h.logs if lvl == "ERROR"]
    assert "flood: scan 1 fault: polarizer/state" in errors[0]
    assert any("flood: scan 1: node 'simulator' lost: no heartbeat" in t for t in errors), errors
