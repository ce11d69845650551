"""What a respawned node restores from the launch's run directory (runtime/liveness.py ``RunState``): the
emitter's scan ids go on, the simulator's source stays where the plan put it, the polarizer keeps its
calibration, the planner the medium of its last re-plan. Each node through the harness, twice in one run
directory: the second is the respawned one."""

import pytest
from polarstripe.msgs import Empty, MediumEstimate, Plan, ScanRequest
from polarstripe.nodes.emitter import Emitter
from polarstripe.nodes.planner import Planner
from polarstripe.nodes.polarizer import Polarizer
from polarstripe.nodes.simulator import Simulator
from polarstripe.runtime.testing import NodeHarness


def in_run(cls, run_dir, incarnation):
    """``cls`` started by a launch whose run directory is ``run_dir``, as its ``incarnation``."""

    class InRun(cls):
        def setup(self):
            self._bus.graph = {"run_dir": str(run_dir)}  # what the launcher's graph gives a node
            self.incarnation = incarnation  # what the runner sets from $POLARSTRIPE_INCARNATION
            super().setup()

    return InRun


def test_a_respawned_emitter_never_reuses_a_scan_id(tmp_path):
    first = NodeHarness(in_run(Emitter, tmp_path, 0), name="emitter", namespace="/rig")
    ids = [first.call("emitter/start_scan", ScanRequest(method="flood")).scan_id for _ in range(2)]
    again = NodeHarness(in_run(Emitter, tmp_path, 1), name="emitter", namespace="/rig")
    ids.append(again.call("emitter/start_scan", ScanRequest(method="flood")).scan_id)
    assert ids == [1, 2, 3]
    assert any("incarnation 1: scan ids go on from 3" in t for _, t in again.logs)
    alone = NodeHarness(Emitter, name="emitter", namespace="/rig")  # no launch: from 1
    assert alone.call("emitter/start_scan", ScanRequest(method="flood")).scan_id == 1


def test_a_respawned_simulator_keeps_the_planned_source_position(tmp_path):
    params = {"resolution": "48x36", "seed": 3}
    first = NodeHarness(in_run(Simulator, tmp_path, 0), name="simulator", namespace="/rig", params=params)
    default = first.node.scene.separation_m()
    assert first.call("simulator/move_source", Plan(modality="flood", separation_m=0.35)).ok
    again = NodeHarness(in_run(Simulator, tmp_path, 1), name="simulator", namespace="/rig", params=params)
    assert default != pytest.approx(0.35)
    assert again.node.scene.separation_m() == pytest.approx(0.35)
    assert again.node.truth().metrics["separation_m"] == pytest.approx(0.35)
    assert any("source restored to d_LC = 0.350 m" in t for _, t in again.logs)


def test_a_respawned_polarizer_keeps_its_calibration(tmp_path):
    params = {"stage": "sim", "min_deg": -90.0, "max_deg": 90.0}
    first = NodeHarness(in_run(Polarizer, tmp_path, 0), name="polarizer", namespace="/rig", params=params)
    assert first.node.least_backscatter_deg is None
    first.node.least_backscatter_deg = 12.5  # as a calibration's fit sets it
    first.stop()
    again = NodeHarness(in_run(Polarizer, tmp_path, 1), name="polarizer", namespace="/rig", params=params)
    assert again.node.least_backscatter_deg == 12.5
    assert again.node._calibrations == 1 << 16  # its calibration scan ids are not the first one's
    again.stop()


def test_a_respawned_planner_plans_with_the_medium_it_had_measured(tmp_path):
    fast = {"fidelity": "preview", "separations": 4, "d_min_m": 0.05, "d_max_m": 0.45,
            "resolution": "160x120", "publish_on_start": False}
    first = NodeHarness(in_run(Planner, tmp_path, 0), name="planner", namespace="/rig", params=fast)
    default_p = first.node.p_assumed
    first.deliver("medium/estimate", MediumEstimate(p=0.2, scan_id=1))
    assert first.node.counters["replans"] == 1
    again = NodeHarness(in_run(Planner, tmp_path, 1), name="planner", namespace="/rig", params=fast)
    assert default_p != pytest.approx(0.2, abs=0.05)
    # the DOP model that gives the measured p where it was measured (planning/medium_dop.py), restored
    measured = first.node.scene.medium.dop.depolarization
    assert measured > 0.2 and again.node.scene.medium.dop.depolarization == pytest.approx(measured, abs=1e-9)
    assert again.call("planner/plan", Empty()).separation_m == first.node.plan.separation_m


def test_the_simulator_at_reference_fidelity_beats_once_a_second():
    """Its compiled kernels hold the GIL for up to ~1.1 s at reference (320x240): a 0.25 s beat would miss
    its 1 s deadline while the node is alive."""
    h = NodeHarness(Simulator, name="simulator", params={"resolution": "16x12", "fidelity": "reference"})
    assert h.node.heartbeat().counters["heartbeat_ms"] == 1000
    h = NodeHarness(Simulator, name="simulator", params={"resolution": "16x12"})
    assert h.node.heartbeat().counters["heartbeat_ms"] == 250
