"""The compositor fed a polarization camera's raw mosaic frames (Frame.mosaic_deg), one per stripe: E_b and
E_w come from each frame, eq. 6 gives S back; the same scene as tests/nodes/test_compositor.py's, written
through Malus's law per pixel (sim/mosaic.py's model, not its code)."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.msgs import Frame, ScanEvent
from polarstripe.nodes.compositor import Compositor
from polarstripe.runtime.testing import NodeHarness

H, W, DARK, ER = 48, 64, 64, 300.0
LAYOUT = [90.0, 45.0, 135.0, 0.0]


def _harness(**params):
    base = {"dark_offset_dn": float(DARK), "use_truth": False, "done_grace_s": 0.05,
            "object_free_roi": [0, H, 0, 16], "mosaic_extinction_ratio": ER, "mosaic_crosstalk": [0.0, 0.0]}
    return NodeHarness(Compositor, name="compositor", namespace="/rig", params={**base, **params})


def _scene():
    s = np.zeros((H, W))
    s[:, 16:] = 400.0
    s[8:24, 16:] = 1200.0
    return s


def _mosaic(s, b, p, chi_deg):
    """Unpolarized s plus backscatter b of DOP p at chi through each pixel's micro-polarizer, in DN."""
    phi = np.radians(np.tile(np.reshape(LAYOUT, (2, 2)), (H // 2, W // 2)))
    k2 = 1 / ER
    raw = 0.5 * (1 + k2) * (s + b) + 0.5 * (1 - k2) * b * p * np.cos(2 * (phi - np.radians(chi_deg)))
    return np.round(raw + DARK).astype(np.uint16)


def _scan(h, method, images, patterns):
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="start", method=method, stripes=len(images)
                                        if method.endswith("stripes") else 0))
    for step, (image, pattern) in enumerate(zip(images, patterns, strict=True)):
        h.deliver("camera/frame", Frame(image=image, exposure_s=0.01, pattern=pattern, scan_id=1, step=step,
                                        mosaic_deg=LAYOUT))
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="done", method=method))
    return h.published("compositor/composite")[-1]


def _inside(a):
    """Pixels two or more away from the scene's edges and the frame's (bilinear demosaicing blurs 1 px)."""
    keep = np.zeros((H, W), bool)
    for r0, r1 in ((2, 6), (10, 22), (26, 46)):
        for c0, c1 in ((2, 14), (18, 26), (30, 38), (42, 50), (54, 62)):   # stripe edges 16, 28, 40, 52
            keep[r0:r1, c0:c1] = True
    return a[keep]


@pytest.mark.parametrize("rule", ["local", "global", "pixel"])
def test_polarized_stripes_from_one_mosaic_frame_per_stripe_recover_s_and_p(rule):
    s, b, p, chi, n = _scene(), 1000.0, 0.8, 20.0, 4
    edges = np.linspace(16, W, n + 1).astype(int)
    frames = []
    for k in range(n):
        lit = np.zeros((H, W))
        lit[:, edges[k]:edges[k + 1]] = 1.0
        frames.append(_mosaic(s * lit, b, p, chi))
    h = _harness(mosaic_rule=rule)
    comp = _scan(h, "polarized_stripes", frames, [f"stripe:{k}/{n}" for k in range(n)])
    a0 = 0.5 * (1 + 1 / ER)
    assert comp.metrics["frames"] == n and comp.metrics["mosaic"] == {"layout_deg": LAYOUT, "rule": rule}
    assert comp.metrics["p"] == pytest.approx(p, abs=3e-3)
    # eq. 6 on E_b = a0 (S + B(1 - p)), E_w = a0 (S + B(1 + p)): 2 a0 S (S, as with a rotating analyzer)
    np.testing.assert_allclose(_inside(comp.images["composite"]), _inside(2 * a0 * s), atol=4.0)
    np.testing.assert_allclose(_inside(comp.images["e_b"]), _inside(a0 * (s + b * (1 - p))), atol=1.5)
    assert h.node.counters["frames_bad"] == 0


def test_an_unpolarized_method_takes_the_mosaics_intensity():
    s, b = _scene(), 300.0
    h = _harness()
    comp = _scan(h, "flood", [_mosaic(s, b, 0.8, 50.0)], ["flood"])
    np.testing.assert_allclose(_inside(comp.images["composite"]), _inside(0.5 * (1 + 1 / ER) * (s + b)),
                               atol=1.5)


def test_a_mosaic_frame_in_a_rotating_analyzers_scan_or_of_odd_size_is_dropped():
    h = _harness()
    h.deliver("emitter/scan", ScanEvent(scan_id=2, event="start", method="polarized_flood",
                                        analyzer_deg=[0.0, 90.0]))
    h.deliver("camera/frame", Frame(image=_mosaic(_scene(), 100.0, 0.5, 0.0), exposure_s=0.01,
                                    pattern="flood", scan_id=2, step=0, mosaic_deg=LAYOUT))
    assert h.node.counters["frames_bad_angle"] == 1
    h.deliver("emitter/scan", ScanEvent(scan_id=3, event="start", method="flood"))
    h.deliver("camera/frame", Frame(image=np.zeros((7, 8), np.uint16), exposure_s=0.01, pattern="flood",
                                    scan_id=3, step=0, mosaic_deg=LAYOUT))
    assert h.node.counters["frames_bad"] == 1
