"""The compositor's depth through the harness: a stripe scan of the default tank's back wall (z = 0.38 m,
drawn here in closed form from the projector's pose) comes back as that depth, on the topic and in files;
with K sheets per frame (stripe:I/N:xK) too, in a K-th of the frames."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.msgs import Frame, ScanEvent
from polarstripe.msgs.patterns import sheet_positions, stripes
from polarstripe.nodes.compositor import Compositor
from polarstripe.nodes.compositor_depth import read_ply, write_calibration
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


def _frames(z=0.38):
    """Stripe frames of a wall at depth z: the lit fraction of each pixel's sub-samples."""
    cols = _columns(z)
    edges = np.arange(N + 1) * 1024 // N
    rng = np.random.default_rng(0)
    for k in range(N):
        lit = ((cols >= edges[k]) & (cols < edges[k + 1])).mean(axis=0)
        yield np.round(DARK + 50 + 2000 * lit + rng.normal(0, 2, (H, W))).astype(np.uint16), f"stripe:{k}/{N}"


def _run(tmp_path, **params):
    h = NodeHarness(Compositor, name="compositor", namespace="/rig",
                    params={"dark_offset_dn": float(DARK), "use_truth": False, "done_grace_s": 0.05,
                            "out": str(tmp_path), **params})
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="start", method="stripes", stripes=N))
    for step, (img, pat) in enumerate(_frames()):
        h.deliver("camera/frame", Frame(image=img, exposure_s=0.01, pattern=pat, scan_id=1, step=step))
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="done", method="stripes", stripes=N))
    return h


def test_stripe_scan_depth_is_the_wall(tmp_path):
    h = _run(tmp_path)
    d = h.published("compositor/depth")[-1]
    assert d.method == "stripes" and d.scan_id == 1 and d.depth_m.shape == (H, W)
    ok = np.isfinite(d.depth_m)
    assert ok.mean() > 0.5
    assert np.sqrt(np.mean((d.depth_m[ok] - 0.38) ** 2)) < 1.5e-3
    z = np.load(tmp_path / "depth_stripes.npy")
    np.testing.assert_array_equal(np.isfinite(z), ok)
    pts = read_ply(str(tmp_path / "depth_stripes.ply"))
    assert pts.shape == (ok.sum(), 3)
    np.testing.assert_allclose(pts[:, 2], 0.38, atol=5e-3)
    assert h.published("compositor/composite")[-1].metrics["depth"]["valid_pixels"] == ok.sum()


def test_calibration_file_gives_the_same_depth(tmp_path):
    g = rig_geometry(load_scene(None))
    path = tmp_path / "rig.yaml"
    write_calibration(str(path), g)
    a = _run(tmp_path / "a").published("compositor/depth")[-1].depth_m
    b = _run(tmp_path / "b", geometry=str(path)).published("compositor/depth")[-1].depth_m
    np.testing.assert_allclose(a, b, rtol=1e-5)
    assert _run(tmp_path / "c", geometry="none").published("compositor/depth") == []


def test_bad_geometry_file_is_one_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("%YAML:1.0\n---\nK_cam: 3\n")
    with pytest.raises(Exception, match="geometry"):
        _run(tmp_path, geometry=str(bad))
    with pytest.raises(Exception, match="no such file"):
        _run(tmp_path, geometry=str(tmp_path / "missing.yaml"))


# ---- K sheets per frame (stripe:I/N:xK): each frame lights the union of its sheets' columns ----------
def _run_sheets(sheets, **params):
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
    one = _run_sheets(1).published("compositor/depth")[-1].depth_m
    h = _run_sheets(3, depth_range_m=[0.3, 0.45])
    comp = h.published("compositor/composite")[-1]
    d = h.published("compositor/depth")[-1].depth_m
    ok = np.isfinite(d)
    assert comp.metrics["frames"] == 6 and comp.metrics["sheets"] == 3        # ⌈16/3⌉ frames
    assert comp.metrics["depth"]["depth_range_m"] == [0.3, 0.45]
    assert ok.mean() > 0.5 and ok.sum() >= 0.97 * np.isfinite(one).sum()
    assert np.sqrt(np.mean((d[ok] - 0.38) ** 2)) < 1.5e-3


def test_sheets_that_overlap_in_the_image_are_one_clear_error_and_no_depth():
    h = _run_sheets(3, depth_range_m=[0.1, 0.45])
    assert h.published("compositor/depth") == []
    err = h.published("compositor/composite")[-1].metrics["depth"]["error"]
    assert "3 sheets of 16 stripes overlap in the image" in err and "use at most" in err
    h = _run_sheets(3)                                   # no range and no truth: said, not guessed
    assert "needs the depth range" in h.published("compositor/composite")[-1].metrics["depth"]["error"]
