"""The compositor's depth of a scan with K sheets per frame (stripe:I/N:xK): the default tank's back wall
(z = 0.38 m) drawn in closed form from the projector's pose, as tests/nodes/test_compositor_depth.py draws
one sheet per frame; each K-sheet frame lights the union of its sheets' columns."""

from __future__ import annotations

import numpy as np
from polarstripe.msgs import Frame, ScanEvent
from polarstripe.msgs.patterns import sheet_positions, stripes
from polarstripe.nodes.compositor import Compositor
from polarstripe.runtime.testing import NodeHarness
from polarstripe.sim.depth_truth import rig_geometry
from polarstripe.sim.scene import load_scene

H, W, N, DARK = 48, 64, 16, 64


def _columns(z=0.38):
    """Pattern column of each pixel's 4×4 sub-samples on a wall at depth z, (16, H, W)."""
    g = rig_geometry(load_scene(None))
    f = g["K_cam"][0, 0] * W / 640
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    rr, cc = np.mgrid[0:H, 0:W].astype(float)
    cols = []
    for dy in sub:
        for dx in sub:
            v = np.stack([(cc + dx - (W / 2 - 0.5)) / f, (rr + dy - (H / 2 - 0.5)) / f, np.ones((H, W))], -1)
            p = (v * z) @ g["R"].T + g["T"]
            cols.append(g["K_proj"][0, 0] * p[..., 0] / p[..., 2] + g["K_proj"][0, 2] + 0.5)
    return np.stack(cols)


def _run(sheets, **params):
    cols = _columns()
    edges = np.arange(N + 1) * 1024 // N
    rng = np.random.default_rng(0)
    h = NodeHarness(Compositor, name="compositor", namespace="/rig",
                    params={"dark_offset_dn": float(DARK), "use_truth": False, "done_grace_s": 0.05,
                            **params})
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="start", method="stripes", stripes=N, sheets=sheets))
    for step, pat in enumerate(stripes(N, sheets)):
        lit = sum(((cols >= edges[k]) & (cols < edges[k + 1])).mean(axis=0) for k in sheet_positions(pat))
        img = np.round(DARK + 50 + 2000 * lit + rng.normal(0, 2, (H, W))).astype(np.uint16)
        h.deliver("camera/frame", Frame(image=img, exposure_s=0.01, pattern=str(pat), scan_id=1, step=step))
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="done", method="stripes", stripes=N, sheets=sheets))
    return h


def test_three_sheets_per_frame_give_the_wall_in_a_third_of_the_frames():
    one = _run(1).published("compositor/depth")[-1].depth_m
    h = _run(3, depth_range_m=[0.3, 0.45])
    comp = h.published("compositor/composite")[-1]
    d = h.published("compositor/depth")[-1].depth_m
    ok = np.isfinite(d)
    assert comp.metrics["frames"] == 6 and comp.metrics["sheets"] == 3        # ⌈16/3⌉ frames
    assert comp.metrics["depth"]["depth_range_m"] == [0.3, 0.45]
    assert ok.mean() > 0.5 and ok.sum() >= 0.97 * np.isfinite(one).sum()
    assert np.sqrt(np.mean((d[ok] - 0.38) ** 2)) < 1.5e-3


def test_sheets_that_overlap_in_the_image_are_one_clear_error_and_no_depth():
    h = _run(3, depth_range_m=[0.1, 0.45])
    assert h.published("compositor/depth") == []
    err = h.published("compositor/composite")[-1].metrics["depth"]["error"]
    assert "3 sheets of 16 stripes overlap in the image" in err and "use at most" in err
    h = _run(3)                                   # no range and no truth: said, not guessed
    assert "needs the depth range" in h.published("compositor/composite")[-1].metrics["depth"]["error"]
