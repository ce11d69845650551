"""The sequencer's rescan (nodes/sequencer.py step 4, nodes/sequencer_rescan.py) through the harness: with an
estimator in the launch graph, a pass waits for the estimate of one of its scans and the plan answering it; a
plan more than one grid step away moves the source and scans the methods again, once; one step or less does
not."""

import numpy as np
from polarstripe.msgs import Ack, Composite, Heartbeat, MediumEstimate, Plan, ScanEvent
from polarstripe.nodes.sequencer import Sequencer
from polarstripe.runtime.testing import NodeHarness

GRID = np.array([0.1, 0.2, 0.3, 0.4, 0.5])


def _plan(sep, answers=None, objective=None, grid=GRID):
    curves = {"separation_m": grid}
    if objective is not None:
        curves["objective"] = np.asarray(objective, float)
    if answers is not None:
        curves["estimate_scan_id"] = np.array([float(answers)])
    return Plan(modality="stripes", separation_m=sep, curves=curves)


def rig(replan_to: float | None, graph=("estimator", "planner"), objective=None, grid=GRID, **params):
    """Scans end at once; after each stripes scan the estimator's estimate and then (if ``replan_to``) the
    planner's plan at ``replan_to`` in answer to it arrive, after plans that answer something else."""
    h = NodeHarness(Sequencer, name="sequencer", namespace="/rig",
                    params={"methods": ["flood", "stripes"], "stripes": 5, "calibrate": False, **params})
    h.bus.graph = {"nodes": {"sequencer": {}, **{n: {} for n in graph}}}
    for n in graph:
        h.queue("heartbeat", Heartbeat(node=n, pid=1, uptime_s=1.0, counters={"heartbeat_ms": 250}))
    h.calls = []
    h.on_call("planner/plan", lambda req: h.calls.append("plan") or _plan(0.3))
    h.on_call("simulator/move_source", lambda req: h.calls.append(f"move {req.separation_m}") or Ack(ok=True))

    def start(req):
        sid = len([c for c in h.calls if c.startswith("scan")]) + 1
        h.calls.append(f"scan {req.method} {sid}")
        h.queue("emitter/scan", ScanEvent(scan_id=sid, event="done", method=req.method))
        h.queue("compositor/composite", Composite(images={"c": np.zeros((2, 2))}, method=req.method,
                                                  scan_id=sid, metrics={"contrast": 0.5}))
        if req.method == "stripes":
            h.queue("medium/estimate", MediumEstimate(p=0.5, sigma_t_per_m=3.0, mean_cosine=0.9, scan_id=sid))
            # a plan published after the estimate but not in answer to it (a re-plan on the compositor's p)
            h.queue("planner/plan", _plan(0.1))
            h.queue("planner/plan", _plan(0.1, answers=sid - 1))
            if replan_to is not None:
                h.queue("planner/plan", _plan(replan_to, answers=sid, objective=objective, grid=grid))
        return ScanEvent(scan_id=sid, event="start", method=req.method)

    h.on_call("emitter/start_scan", start)
    return h


def test_a_plan_two_steps_away_moves_the_source_and_rescans_once():
    h = rig(0.5)
    h.node.run()
    assert h.node.exit_code == 0, h.logs
    assert h.calls == ["plan", "move 0.3", "scan flood 1", "scan stripes 2", "move 0.5", "scan flood 3",
                       "scan stripes 4"]  # max_rescans 1: the second pass's estimate is not waited for
    assert any("rescanning at d_LC = 0.500 m (the optimum moved by 2 grid steps)" in t for _, t in h.logs)


def test_one_grid_step_is_no_rescan():
    h = rig(0.4)
    h.node.run()
    assert h.node.exit_code == 0
    assert h.calls == ["plan", "move 0.3", "scan flood 1", "scan stripes 2"]
    assert any("plan d_LC = 0.400 m (scanned at 0.300 m, 1 grid steps)" in t for _, t in h.logs)


def test_steps_are_the_grids_spacing_not_the_bisections_points():
    """The planner's curve holds midpoints near its best (planning/planner.py refine): a pick half a step away
    is no rescan, though three points of the curve lie between."""
    h = rig(0.25, grid=np.array([0.1, 0.2, 0.25, 0.2625, 0.275, 0.3, 0.4, 0.5]))
    h.node.run()
    assert h.node.exit_code == 0
    assert h.calls == ["plan", "move 0.3", "scan flood 1", "scan stripes 2"]
    assert any("plan d_LC = 0.250 m (scanned at 0.300 m, 0 grid steps)" in t for _, t in h.logs), h.logs


def test_no_plan_answering_the_estimate_is_no_rescan():
    h = rig(None, estimate_timeout_s=5.0)
    h.node.run()
    assert h.node.exit_code == 0 and "move 0.1" not in h.calls and len(h.calls) == 4
    assert any(lvl == "WARNING" and "no rescan" in t for lvl, t in h.logs)


def test_without_an_estimator_in_the_graph_nothing_is_waited_for():
    h = rig(0.5, graph=("planner",))
    h.node.run()
    assert h.node.exit_code == 0 and h.calls == ["plan", "move 0.3", "scan flood 1", "scan stripes 2"]


def test_a_pick_the_replanned_curve_predicts_no_better_is_no_rescan():
    """The re-made plan moved two steps (its saturation guard, say), but its own curve scores the separation
    scanned higher: rescanning there would cost every method (docs/planning.md §6.1)."""
    h = rig(0.5, objective=[0.5, 0.6, 0.83, 0.82, 0.80])
    h.node.run()
    assert h.node.exit_code == 0
    assert h.calls == ["plan", "move 0.3", "scan flood 1", "scan stripes 2"]
    assert any("objective 0.800 there, 0.830 where scanned" in t for _, t in h.logs)
    assert any("no rescan: the re-made plan predicts no gain" in t for _, t in h.logs)


def test_a_predicted_gain_of_min_gain_or_more_rescans():
    h = rig(0.5, objective=[0.5, 0.6, 0.80, 0.82, 0.82])
    h.node.run()
    assert h.node.exit_code == 0 and "move 0.5" in h.calls
    h = rig(0.5, objective=[0.5, 0.6, 0.80, 0.82, 0.805])   # a gain below the default 0.01
    h.node.run()
    assert "move 0.5" not in h.calls
