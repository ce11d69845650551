"""The estimator node (nodes/estimator.py) through the harness, on frames the model renders at 48x36: a scan
set of a medium the node does not know gives a published estimate within the issue's bounds (σ_t 10 %, mean
cosine 0.05) while the loop keeps running; clear water gives a published "cannot estimate" with the reason.

Each test waits in real time for the worker thread's fit (~2-5 s on this machine)."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
from polarstripe.msgs import Composite, Frame, ScanEvent
from polarstripe.nodes.estimator import Estimator
from polarstripe.runtime.testing import NodeHarness
from polarstripe.sim.polarization import least_backscatter_angle
from polarstripe.sim.render import render_components, render_frame
from polarstripe.sim.scene import Phase, load_scene

W, H, N = 48, 36, 30


def _truth(sigma_t: float, g: float):
    sc = load_scene(None)
    cam = sc.camera
    cam = cam.replace(resolution=(W, H), exposure_s=cam.exposure_s * (W / cam.resolution[0]) ** 2)
    return sc.replace(camera=cam, medium=sc.medium.replace(sigma_t=sigma_t, phase=Phase("tthg", g)))


def _frame(scene, pattern, sid, step, analyzer=None):
    img = render_frame(scene, pattern, analyzer, "preview", seed=100 * sid + step)[0]
    return Frame(image=img, exposure_s=scene.camera.exposure_s, pattern=pattern, polarizer_deg=analyzer,
                 scan_id=sid, step=step)


def _scan(h, sid, method, frames, analyzer_deg=()):
    h.deliver("emitter/scan", ScanEvent(scan_id=sid, event="start", method=method,
                                        analyzer_deg=list(analyzer_deg)))
    for f in frames:
        h.deliver("camera/frame", f)
    h.deliver("emitter/scan", ScanEvent(scan_id=sid, event="done", method=method))


def _wait_estimate(h, timeout_s=120.0):
    t0 = time.monotonic()
    while not h.published("medium/estimate") and time.monotonic() - t0 < timeout_s:
        h.advance(0.2)
        time.sleep(0.05)
    return h.published("medium/estimate")


def test_estimate_of_an_unknown_medium_within_bounds_while_the_loop_runs():
    truth = _truth(3.0, 0.7)
    h = NodeHarness(Estimator, name="estimator", namespace="/rig", params={"resolution": f"{W}x{H}"})
    comp = render_components(truth, "flood", "preview")
    chi = least_backscatter_angle(comp)
    sep = truth.separation_m()
    depth = np.where(comp.object_mask, 1.0, 0.0).astype(np.float32)
    h.deliver("simulator/truth", Composite(images={"depth_m": depth}, method="truth", scan_id=2,
                                           metrics={"separation_m": sep}))
    _scan(h, 1, "flood", [_frame(truth, "flood", 1, 0)])
    pair = [_frame(truth, "flood", 2, 0, chi), _frame(truth, "flood", 2, 1, chi + 90)]
    _scan(h, 2, "polarized_flood", pair, analyzer_deg=(chi, chi + 90))
    stripes = [_frame(truth, f"stripe:{k}/{N}", 3, k) for k in (8, 15, 22)]
    _scan(h, 3, "stripes", stripes)
    # the fit runs in the worker: nothing published yet, and the loop still handles what arrives
    assert h.published("medium/estimate") == [] and h.node.job is not None
    # in a daemon thread: a SIGINT mid-fit ends the process without waiting for it (seen in a launch)
    assert any(t.name == "medium fit" and t.daemon for t in threading.enumerate())
    h.deliver("camera/frame", _frame(truth, "flood", 99, 0))  # a frame of no scan: handled and counted
    assert h.node.counters["frames_ignored"] == 1
    est = _wait_estimate(h)
    assert len(est) == 1, h.logs
    e = est[0]
    assert not e.reason and e.scan_id == 3
    assert abs(e.sigma_t_per_m / 3.0 - 1) <= 0.10 and abs(e.mean_cosine - 0.7) <= 0.05
    assert 0 < e.sigma_t_std < 0.15 * e.sigma_t_per_m and 0 < e.mean_cosine_std < 0.05
    # p against an independent number from the components (tests/planning/test_medium_fit.py): the
    # backscatter's own DOP over the region, which the object's light hides from the frames alone
    free = ~comp.object_mask
    p_true = float(np.sum((comp.B * comp.p)[free]) / np.sum(comp.B[free]))  # the backscatter's DOP
    measured = float(np.median((comp.B * comp.p)[free]) / np.median((comp.D + comp.A + comp.B)[free]))
    assert measured < p_true - 0.05  # what the frames show: the object's light lowers the ratio
    assert abs(e.p - p_true) < 0.05 and 0 < e.p_std < 0.05
    # one fit per source pose: another stripe scan at the same pose is not fitted again
    _scan(h, 4, "polarized_stripes", stripes)
    h.advance(1.0)
    assert h.node.job is None and h.node.pending is None and len(h.published("medium/estimate")) == 1


def test_clear_water_is_a_published_cannot_estimate():
    clear = _truth(0.0, 0.8)  # no backscatter: no visible sheet
    h = NodeHarness(Estimator, name="estimator", namespace="/rig", params={"resolution": f"{W}x{H}"})
    _scan(h, 1, "flood", [_frame(clear, "flood", 1, 0)])
    _scan(h, 2, "stripes", [_frame(clear, f"stripe:{k}/{N}", 2, k) for k in (8, 15, 22)])
    est = _wait_estimate(h)
    assert len(est) == 1
    e = est[0]
    assert "no visible sheet" in e.reason and e.sigma_t_per_m is None and e.mean_cosine is None
    assert math.isnan(e.p) and e.scan_id == 2  # no analyzer pair: no p
    assert h.node.counters["refusals"] == 1 and any("cannot estimate" in t for _, t in h.logs)


def test_frames_of_another_size_are_refused_with_the_reason():
    truth = _truth(3.0, 0.8)
    h = NodeHarness(Estimator, name="estimator", namespace="/rig", params={"resolution": "64x48"})
    _scan(h, 1, "stripes", [_frame(truth, f"stripe:{k}/{N}", 1, k) for k in (8, 15)])
    est = _wait_estimate(h)
    assert len(est) == 1 and "48x36 px" in est[0].reason and "64x48" in est[0].reason
