"""The compositor's depth on frames rendered exactly as the demo renders them: the simulator node itself
(default tank, 320x240, preview, all orders of scattering, the source moved to the planner's separation of
``launch/sim.toml``'s run) feeds a compositor harness a stripe scan and a polarized stripe scan; the depth is
scored against the simulator's own depth truth (sim/depth_truth.py, the chart on the back wall).

Before the windowed edge (imaging/delineation.py) this scene gave ~30 % valid object pixels (4 % with the
older model): the two-pixel edge rule rejected the ramps all orders of scattering make of the stripes.
About 10 s: 30 renders of the model (the polarized scan reuses them); nothing smaller reproduces the demo."""

from __future__ import annotations

import numpy as np
from polarstripe.msgs import Plan, ScanEvent
from polarstripe.msgs.rig import RenderRequest
from polarstripe.nodes.compositor import Compositor
from polarstripe.nodes.simulator import Simulator
from polarstripe.runtime.testing import NodeHarness

N, SEPARATION_M = 30, 0.187  # launch/sim.toml's stripes; the planner's d_LC for the default tank


def test_demo_frames_give_depth_of_most_object_pixels(tmp_path):
    sim = NodeHarness(Simulator, name="simulator", namespace="/rig",
                      params={"resolution": "320x240", "seed": 3})
    assert sim.call("simulator/move_source", Plan(modality="stripes", separation_m=SEPARATION_M)).ok
    comp = NodeHarness(Compositor, name="compositor", namespace="/rig",
                       params={"out": str(tmp_path), "done_grace_s": 0.05})
    for sid, method, angles in ((1, "stripes", [None]), (2, "polarized_stripes", [0.0, 90.0])):
        ev = ScanEvent(scan_id=sid, event="start", method=method, stripes=N,
                       analyzer_deg=[a for a in angles if a is not None])
        sim.deliver("emitter/scan", ev)
        truth = sim.published("simulator/truth")[-1]
        comp.deliver("simulator/truth", truth)
        comp.deliver("emitter/scan", ev)
        for k in range(N):
            for j, a in enumerate(angles):
                sim.node.analyzer_angle = (lambda a=a: a)  # the drive's position, as the polarizer sets it
                req = RenderRequest(pattern=f"stripe:{k}/{N}", analyzer=a is not None, scan_id=sid,
                                    step=k * len(angles) + j)
                comp.deliver("camera/frame", sim.call("simulator/render", req))
        comp.deliver("emitter/scan", ScanEvent(scan_id=sid, event="done", method=method, stripes=N))
        comp.advance(1.0)
        d = comp.published("compositor/depth")[-1]
        assert d.method == method and d.metrics["geometry"] == "simulator/truth"
        zt = np.where(truth.images["depth_m"] > 0, truth.images["depth_m"], np.nan)
        ok, obj = np.isfinite(d.depth_m), np.isfinite(zt)
        err = (d.depth_m - zt)[ok & obj]
        assert (ok & obj).sum() / obj.sum() > 0.6, (method, d.metrics)
        assert np.sqrt(np.mean(err ** 2)) < 8e-3 and np.median(np.abs(err)) < 3.5e-3, (method, d.metrics)
        assert (ok & ~obj).sum() < 0.01 * (~obj).sum()  # no depth invented in the open water
        assert d.metrics["valid_fraction_of_objects"] == (ok & obj).sum() / obj.sum()
