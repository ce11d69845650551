"""The emitter through the node harness: scan order, tags, analyzer handling and every fault path ends in a
published fault (virtual clock: timeouts cost no real time); its services are answered while a scan runs."""

import numpy as np
import pytest
from polarstripe.msgs import Ack, Frame, PolarizerState, ScanRequest
from polarstripe.nodes.drivers.display import render_pattern
from polarstripe.nodes.emitter import Emitter
from polarstripe.runtime.testing import NodeHarness


def make(params=None, *, frames=True, settle=True):
    """An emitter whose grabber answers every trigger (queuing the frame unless ``frames`` is False) and
    whose polarizer settles at every commanded angle (unless ``settle`` is False)."""
    h = NodeHarness(Emitter, name="emitter", namespace="/rig", params={"stripes": 4, **(params or {})})
    mounts = []

    def polarizer(cmd):  # the stage reports settled at each commanded angle
        if settle:
            a = cmd.target_deg
            h.queue("polarizer/state", PolarizerState(angle_deg=a, target_deg=a, settled=True))

    def trigger(req):
        if frames:
            h.queue("camera/frame", Frame(image=np.zeros((2, 3), np.uint16), exposure_s=0.01,
                                          pattern=req.pattern, scan_id=req.scan_id, step=req.step))
        return Ack(ok=True)

    h.on_call("camera/trigger", trigger)
    h.on_call("camera/analyzer", lambda req: mounts.append(req.inserted) or Ack(ok=True))
    h.on_publish("polarizer/cmd", polarizer)
    h.mounts = mounts
    return h


def run(h, request, limit_s=60.0):
    """Start a scan, run the loop until it has ended (or ``limit_s`` of virtual time), return (reply,
    emitter/scan events)."""
    reply = h.call("emitter/start_scan", request)
    h.advance(0.05)
    t0 = h.bus.now()
    while h.node.scanning is not None or h.node.queue:
        assert h.bus.now() - t0 < limit_s, "the scan never ended"
        h.advance(0.05)
    return reply, h.published("emitter/scan")


def triggers(h):
    return h.bus.clients[h.full("camera/trigger")].requests


def test_polarized_stripes_order_tags_and_angles():
    h = make()
    reply, events = run(h, ScanRequest(method="polarized_stripes", analyzer_deg=[10.0]))
    assert reply.event == "start" and reply.scan_id == 1 and reply.analyzer_deg == [10.0, 100.0]
    assert [e.event for e in events] == ["start", "done"]
    assert [c.target_deg for c in h.published("polarizer/cmd")] == [10.0, 100.0]
    tags = [f"stripe:{k}/4" for k in range(4)]
    assert [(r.step, r.pattern) for r in triggers(h)] == list(enumerate(tags * 2))
    pats = h.published("emitter/pattern")
    assert [(p.kind, p.index, p.count, p.step) for p in pats] == [("stripe", k % 4, 4, k) for k in range(8)]
    assert h.node.display.current.kind == "off"  # blanked after the scan
    assert h.mounts == []  # the analyzer stays in the path for polarized methods


def test_unpolarized_scan_takes_the_analyzer_out_and_puts_it_back():
    h = make()
    reply, events = run(h, ScanRequest(method="flood"))
    assert reply.analyzer_deg == [] and [e.event for e in events] == ["start", "done"]
    assert h.mounts == [False, True]
    assert h.published("polarizer/cmd") == []
    assert [r.pattern for r in triggers(h)] == ["flood"]


@pytest.mark.parametrize("method", ["polarized_stripes", "stripes"])
def test_with_a_polarization_camera_a_scan_is_one_pass_without_analyzer_moves_or_mounts(method):
    h = make({"analyzer": "mosaic"})
    reply, events = run(h, ScanRequest(method=method, analyzer_deg=[10.0]))
    assert reply.event == "start" and reply.analyzer_deg == []
    assert [e.event for e in events] == ["start", "done"]   # and N frames, not 2N:
    assert [(r.step, r.pattern) for r in triggers(h)] == [(k, f"stripe:{k}/4") for k in range(4)]
    assert h.published("polarizer/cmd") == [] and h.mounts == []


def test_hf_separation_checkers_are_complementary():
    h = make({"checker_size": 8})
    _, events = run(h, ScanRequest(method="hf_separation"))
    assert events[-1].event == "done"
    tags = [r.pattern for r in triggers(h)]
    assert len(tags) == 2
    a, b = (render_pattern(t, 64, 48) > 0 for t in tags)
    assert not (a & b).any() and (a | b).all()  # every projector pixel lit exactly once


def test_frame_that_never_comes_is_a_fault_naming_the_step():
    h = make(frames=False)
    _, events = run(h, ScanRequest(method="stripes"))
    assert [e.event for e in events] == ["start", "fault"]
    assert "step 0 (stripe:0/4)" in events[-1].detail and "camera/frame" in events[-1].detail
    assert h.mounts == [False, True]  # put back despite the fault
    assert h.node.display.current.kind == "off"


def test_stage_that_never_settles_is_a_fault():
    h = make(settle=False)
    _, events = run(h, ScanRequest(method="polarized_flood", analyzer_deg=[0.0, 90.0]))
    assert events[-1].event == "fault" and "not settled at 0 deg" in events[-1].detail
    assert triggers(h) == []  # no frame taken at an unsettled angle


def test_stage_fault_ends_the_scan_at_once():
    h = make(settle=False)
    h.queue("polarizer/state", PolarizerState(angle_deg=float("nan"), target_deg=0.0, settled=False,
                                              fault="EMCY 0x8611"))
    _, events = run(h, ScanRequest(method="polarized_flood", analyzer_deg=[0.0, 90.0]))
    assert events[-1].event == "fault" and "EMCY 0x8611" in events[-1].detail


def test_settled_elsewhere_is_not_settled_here():
    h = make(settle=False)
    h.queue("polarizer/state", PolarizerState(angle_deg=45.0, target_deg=45.0, settled=True))
    _, events = run(h, ScanRequest(method="polarized_flood", analyzer_deg=[0.0, 90.0]))
    assert events[-1].event == "fault" and "not settled" in events[-1].detail


def test_lost_camera_is_reported_in_the_scan_fault():
    h = make()
    h.on_call("camera/trigger", lambda req: Ack(ok=False, detail="DeviceLost: sim camera: gone"))
    _, events = run(h, ScanRequest(method="flood"))
    assert events[-1].event == "fault" and "DeviceLost: sim camera: gone" in events[-1].detail


def test_grabber_not_answering_is_a_fault():
    h = make()
    del h.bus.responders[h.full("camera/trigger")]
    _, events = run(h, ScanRequest(method="flood"))
    assert events[-1].event == "fault" and "camera/trigger" in events[-1].detail


@pytest.mark.parametrize(("request_", "text"), [
    (ScanRequest(method="laser"), "method 'laser' is not one of"),
    (ScanRequest(method="polarized_flood", analyzer_deg=[0.0, 30.0, 60.0]), "needs analyzer_deg"),
    (ScanRequest(method="polarized_flood"), "needs analyzer_deg"),
    (ScanRequest(method="stripes", stripes=-3), "stripes=-3"),
    (ScanRequest(method="flood", analyzer_deg=[float("inf")]), "finite"),
])
def test_bad_requests_are_refused_with_the_reason(request_, text):
    h = make()
    reply = h.call("emitter/start_scan", request_)
    assert reply.event == "fault" and text in reply.detail
    h.advance(0.05)
    assert h.published("emitter/scan") == [] and triggers(h) == []


def test_default_analyzer_angles_and_ids_increase():
    h = make({"analyzer_deg": [5.0, 95.0]})
    first, _ = run(h, ScanRequest(method="polarized_flood"))
    second, events = run(h, ScanRequest(method="flood"))
    assert first.analyzer_deg == [5.0, 95.0] and second.scan_id == first.scan_id + 1
    assert [(e.scan_id, e.event) for e in events] == [(1, "start"), (1, "done"), (2, "start"), (2, "done")]


def test_show_lights_a_pattern_between_scans_and_says_so():
    from polarstripe.msgs import Pattern

    h = make()
    ack = h.call("emitter/show", Pattern(kind="flood", scan_id=7))
    assert ack.ok, ack.detail
    assert h.node.display.current.kind == "flood"
    assert [(p.kind, p.scan_id) for p in h.published("emitter/pattern")] == [("flood", 7)]
    assert h.call("emitter/show", Pattern(kind="off")).ok and h.node.display.current.kind == "off"
    bad = h.call("emitter/show", Pattern(kind="stripe", index=5, count=3))
    assert not bad.ok and bad.detail.startswith("emitter/show: ") and "stripe" in bad.detail
    assert h.node.display.current.kind == "off" and len(h.published("emitter/pattern")) == 2


def test_show_is_refused_while_scans_are_queued():
    from polarstripe.msgs import Pattern

    h = make()
    h.call("emitter/start_scan", ScanRequest(method="flood"))  # queued, not run yet (no timer fired)
    ack = h.call("emitter/show", Pattern(kind="flood"))
    assert not ack.ok and "scan" in ack.detail and h.published("emitter/pattern") == []


def test_services_are_answered_while_a_scan_waits_and_a_stop_ends_it_with_a_fault():
    """The scan is stepped by the loop: while it waits for a frame that never comes, emitter/show is
    refused at once, another scan is queued, and a stop publishes the fault and puts the rig back."""
    from polarstripe.msgs import Pattern

    h = make(frames=False)
    first = h.call("emitter/start_scan", ScanRequest(method="flood"))
    h.advance(0.05)  # started: the trigger answered, the frame is awaited (frame_timeout_s = 5 s)
    assert h.node.scanning is not None and h.node.scanning.scan_id == first.scan_id
    t0 = h.bus.now()
    ack = h.call("emitter/show", Pattern(kind="flood"))
    assert not ack.ok and ack.detail == f"emitter/show: scan {first.scan_id} running"
    second = h.call("emitter/start_scan", ScanRequest(method="stripes"))
    assert second.event == "start" and second.scan_id == first.scan_id + 1
    assert h.bus.now() == t0  # answered at once, mid-scan
    h.advance(1.0)  # still waiting: the frame timeout is 5 s
    assert [e.event for e in h.published("emitter/scan")] == ["start"]
    h.stop("SIGTERM")
    events = h.published("emitter/scan")
    assert [(e.scan_id, e.event) for e in events] == [(1, "start"), (1, "fault")]
    assert events[-1].detail == "step 0 (flood): stopped (SIGTERM) waiting for camera/frame"
    assert h.mounts == [False, True] and h.node.display.current.kind == "off"
    assert [r.pattern for r in triggers(h)] == ["flood"]  # the queued scan never started


def test_a_queued_scan_starts_when_the_running_one_times_out():
    h = make({"frame_timeout_s": 0.5}, frames=False)
    h.call("emitter/start_scan", ScanRequest(method="flood"))
    h.call("emitter/start_scan", ScanRequest(method="flood"))
    h.advance(0.3)
    assert [(e.scan_id, e.event) for e in h.published("emitter/scan")] == [(1, "start")]
    h.advance(0.5)
    events = [(e.scan_id, e.event) for e in h.published("emitter/scan")]
    assert events == [(1, "start"), (1, "fault"), (2, "start")]
    assert "no frame within 0.5 s" in h.published("emitter/scan")[1].detail
