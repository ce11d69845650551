"""The sequencer through the node harness (virtual clock): the order of its calls, and that every failure ends
it with exit status 1 and a line naming the service or topic."""

import numpy as np
import pytest
from polarstripe.msgs import Ack, Composite, Heartbeat, Plan, PolarizerState, ScanEvent
from polarstripe.nodes.sequencer import Sequencer
from polarstripe.runtime.node import NodeStopping
from polarstripe.runtime.params import ParamError
from polarstripe.runtime.testing import NodeHarness


def rig(params=None, *, scans_end="done", composite=True, stage_ok=True, metrics=None):
    """A sequencer whose planner, simulator and emitter answer; each started scan ends with ``scans_end``
    (None: never) and, if ``composite``, gets its composite."""
    h = NodeHarness(Sequencer, name="sequencer", namespace="/rig",
                    params={"methods": ["flood", "polarized_stripes"], "stripes": 5, **(params or {})})
    h.calls = []
    h.on_call("planner/plan",
              lambda req: h.calls.append("plan") or Plan(modality="stripes", separation_m=0.3))
    h.on_call("simulator/move_source",
              lambda req: h.calls.append(f"move {req.separation_m}") or Ack(ok=True))

    def start(req):
        sid = len([c for c in h.calls if c.startswith("scan")]) + 1
        h.calls.append(f"scan {req.method} {req.stripes} {list(req.analyzer_deg)}")
        if scans_end:
            h.queue("emitter/scan", ScanEvent(scan_id=sid, event=scans_end, method=req.method, detail="boom"))
        if composite:
            h.queue("compositor/composite", Composite(images={"c": np.zeros((2, 2))}, method=req.method,
                                                      scan_id=sid, metrics=metrics or {"contrast": 0.5}))
        return ScanEvent(scan_id=sid, event="start", method=req.method)

    h.on_call("emitter/start_scan", start)
    if stage_ok:
        h.queue("polarizer/state", PolarizerState(angle_deg=0.0, target_deg=0.0, settled=True))
    return h


def test_plans_moves_the_source_then_scans_each_method():
    h = rig({"eb_deg": 10.0})
    h.node.run()
    assert h.node.exit_code == 0
    assert h.calls == ["plan", "move 0.3", "scan flood 0 []", "scan polarized_stripes 5 [10.0, 100.0]"]
    assert h.node.results["polarized_stripes"]["metrics"]["contrast"] == 0.5


def test_a_scan_fault_fails_the_sequence_but_the_others_run():
    h = rig(scans_end="fault")
    h.node.run()
    assert h.node.exit_code == 1 and len([c for c in h.calls if c.startswith("scan")]) == 2
    assert any(lvl == "ERROR" and "flood: scan 1 fault: boom" in t for lvl, t in h.logs)


def test_a_scan_that_never_ends_times_out():
    h = rig({"scan_timeout_s": 3.0}, scans_end=None)
    h.node.run()
    assert h.node.exit_code == 1
    assert any("no done/fault on emitter/scan within 3 s" in t for _, t in h.logs)


def test_missing_composite_times_out():
    h = rig({"composite_timeout_s": 2.0, "methods": ["flood"]}, composite=False)
    h.node.run()
    assert h.node.exit_code == 1 and any("no compositor/composite within 2 s" in t for _, t in h.logs)


def test_planner_that_never_answers_ends_the_sequence():
    h = rig({"startup_timeout_s": 5.0})
    del h.bus.responders[h.full("planner/plan")]
    h.node.run()
    assert h.node.exit_code == 1 and "scan flood 0 []" not in h.calls
    assert any(lvl == "ERROR" and t.startswith("planner/plan:") for lvl, t in h.logs)


def test_stage_never_ready_stops_before_polarized_scans():
    h = rig({"startup_timeout_s": 2.0, "plan": False}, stage_ok=False)
    h.queue("polarizer/state", PolarizerState(angle_deg=float("nan"), target_deg=0.0, settled=False,
                                              fault="no heartbeat"))
    h.node.run()
    assert h.node.exit_code == 1 and h.calls == []
    assert any("not ready within 2 s (last fault: no heartbeat)" in t for _, t in h.logs)


def test_with_a_polarization_camera_there_is_no_stage_to_wait_for_calibrate_or_turn():
    h = rig({"startup_timeout_s": 2.0, "analyzer": "mosaic", "calibrate": True}, stage_ok=False)
    h.node.run()
    assert h.node.exit_code == 0
    assert h.calls == ["plan", "move 0.3", "scan flood 0 []", "scan polarized_stripes 5 []"]


def test_without_plan_or_composites():
    h = rig({"plan": False, "wait_composite": False, "methods": ["stripes"]}, composite=False)
    h.node.run()
    assert h.node.exit_code == 0 and h.calls == ["scan stripes 5 []"]


def test_a_composite_with_an_error_fails_the_scan():
    h = rig({"plan": False, "methods": ["flood", "stripes"]}, metrics={"error": "no frames to composite"})
    h.node.run()
    assert h.node.exit_code == 1 and len([c for c in h.calls if c.startswith("scan")]) == 2
    assert h.node.results["flood"]["event"] == "composite_error"
    assert any(lvl == "ERROR" and "flood: scan 1: compositor/composite error: no frames to composite" in t
               for lvl, t in h.logs)


def test_the_results_table_lists_each_method_with_its_scores():
    h = rig(metrics={"contrast": 0.4125, "error_vs_truth": 0.25, "frames": 20, "sheets": 3,
                     "depth": {"valid_fraction": 0.3, "valid_fraction_of_objects": 0.7512,
                               "depth_rms_mm": 1.234}})
    h.node.run()
    table = next(t for lvl, t in h.logs if t.startswith("results:")).splitlines()
    assert table[1].split() == ["method", "frames", "sheets", "contrast", "error", "vs", "truth", "depth",
                                "valid", "RMS", "mm"]
    assert [row.split() for row in table[2:]] == [["flood", "20", "3", "0.412", "0.250", "0.751", "1.23"],
                                                  ["polarized_stripes", "20", "3", "0.412", "0.250", "0.751",
                                                   "1.23"]]


def test_it_waits_until_every_node_of_the_graph_is_heard_before_the_first_step():
    h = rig({"methods": ["flood"], "plan": False})
    h.bus.graph = {"nodes": {"sequencer": {}, "simulator": {}, "emitter": {}}}
    h.queue("heartbeat", Heartbeat(node="emitter", pid=1, uptime_s=0.1))
    h.queue("heartbeat", Heartbeat(node="simulator", pid=2, uptime_s=0.1))
    h.node.run()
    assert h.node.exit_code == 0 and h.calls == ["scan flood 0 []"]


def test_a_node_never_heard_fails_the_sequence_before_any_scan():
    h = rig({"methods": ["flood"], "plan": False, "startup_timeout_s": 2.0})
    h.bus.graph = {"nodes": {"sequencer": {}, "simulator": {}, "emitter": {}}}
    h.queue("heartbeat", Heartbeat(node="emitter", pid=1, uptime_s=0.1))
    h.node.run()
    assert h.node.exit_code == 1 and h.calls == []
    assert any("heartbeat: simulator not heard within 2 s" in t for _, t in h.logs)


def test_a_node_beating_in_its_setup_is_waited_for_beyond_the_startup_timeout():
    """Start-up is tied to readiness: a node heard "starting" (the planner plans in its setup) is waited for
    past ``startup_timeout_s`` while it beats; the first scan comes only after its first ready beat."""
    h = rig({"methods": ["flood"], "plan": False, "startup_timeout_s": 2.0})
    h.bus.graph = {"nodes": {"sequencer": {}, "planner": {}}}
    beats = [(t / 10, {"starting": 1}) for t in range(0, 50, 2)] + [(5.0, {})]  # 5 s starting, then ready
    take = h.bus.take

    def beating(source, timeout_s):  # the planner's beats arrive on the virtual clock
        while beats and beats[0][0] <= h.bus.clock:
            t, counters = beats.pop(0)
            h.queue("heartbeat", Heartbeat(node="planner", pid=1, uptime_s=t, counters=counters))
        return take(source, timeout_s)

    h.bus.take = beating
    h.node.run()
    assert h.node.exit_code == 0 and h.calls == ["scan flood 0 []"]
    assert h.node.now() >= 5.0


def test_a_node_that_stops_beating_in_its_setup_is_named():
    h = rig({"methods": ["flood"], "plan": False, "startup_timeout_s": 2.0})
    h.bus.graph = {"nodes": {"sequencer": {}, "planner": {}}}
    h.queue("heartbeat", Heartbeat(node="planner", pid=1, uptime_s=0.1, counters={"starting": 1}))
    h.node.run()
    assert h.node.exit_code == 1 and h.calls == []
    assert any("node 'planner' lost during its start-up: no heartbeat for 10" in t for _, t in h.logs), h.logs


def test_a_service_gets_one_client_however_many_scans_call_it():
    """A client is a socket: one per call grew a soak's sequencer by ~15 KB a scan (bench soak)."""
    h = rig({"repeat": 3, "plan": False})
    made = []
    client = h.bus.client

    def counting(service, req, resp, timeout_s):
        made.append(service)
        return client(service, req, resp, timeout_s)

    h.bus.client = counting
    h.node.run()
    scans = [c for c in h.calls if c.startswith("scan")]
    assert len(scans) >= 6, h.calls  # 3 passes over the methods
    assert made.count(h.node.resolve("emitter/start_scan")) == 1, made


def test_repeat_runs_the_methods_that_many_times_and_zero_until_stopped():
    h = rig({"repeat": 3, "plan": False})
    h.node.run()
    scans = [c.split()[1] for c in h.calls if c.startswith("scan")]
    assert h.node.exit_code == 0 and scans == ["flood", "polarized_stripes"] * 3

    h = rig({"repeat": 0, "plan": False})
    start = h.bus.responders[h.full("emitter/start_scan")]
    h.on_call("emitter/start_scan",
              lambda req: (h.node.stop("enough") if len(h.calls) >= 7 else None) or start(req))
    with pytest.raises(NodeStopping):  # (the runner ends the node on it)
        h.node.run()  # scans until stopped: the stop comes with the 8th start
    assert len([c for c in h.calls if c.startswith("scan")]) == 8


def test_a_negative_repeat_is_refused():
    with pytest.raises(ParamError, match="repeat must be >= 0"):
        NodeHarness(Sequencer, name="sequencer", params={"repeat": -1})
