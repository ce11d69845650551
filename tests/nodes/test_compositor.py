"""The compositor node through the harness on synthetic frames whose composites are known in closed form.

Scenes are built so the answer is exact: a stripe lights each column block once over a constant backscatter
(max composite = S + b); polarized frames follow eqs. 4-5 with S = 0 in an object-free region (p and S come
back exactly); complementary checkers give L+ = D + G/2, L- = G/2 (direct = D).
"""

from __future__ import annotations

import json
import tracemalloc

import cv2
import numpy as np
import pytest
from polarstripe.msgs import CALIBRATION_SCAN_ID, Composite, Frame, ScanEvent
from polarstripe.nodes.compositor import Compositor
from polarstripe.runtime.testing import NodeHarness

H, W, DARK = 24, 32, 64


def _harness(**params):
    base = {"dark_offset_dn": float(DARK), "use_truth": False, "done_grace_s": 0.05}
    return NodeHarness(Compositor, name="compositor", namespace="/rig", params={**base, **params})


def _scene():
    """S: an object (chart) on the right part, 0 on the left 8 columns (object-free)."""
    s = np.zeros((H, W))
    s[:, 8:] = 400.0
    s[4:12, 8:] = 1200.0  # bright bars on top, dark below
    return s


def _scan(h, scan_id, method, frames, *, stripes=0, analyzer=()):
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="start", method=method, stripes=stripes,
                                        analyzer_deg=list(analyzer)))
    for step, (image, pattern, angle) in enumerate(frames):
        h.deliver("camera/frame", Frame(image=image, exposure_s=0.01, pattern=pattern, polarizer_deg=angle,
                                        scan_id=scan_id, step=step))
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="done", method=method, stripes=stripes,
                                        analyzer_deg=list(analyzer)))
    return h.published("compositor/composite")[-1]


def _dn(x):
    return np.round(x + DARK).astype(np.uint16)


def _stripe_frames(s, b, n, angle=None, scale=1.0):
    edges = np.linspace(0, W, n + 1).astype(int)
    for k in range(n):
        lit = np.zeros((H, W))
        lit[:, edges[k]:edges[k + 1]] = 1.0
        yield _dn(scale * (s * lit + b)), f"stripe:{k}/{n}", angle


def test_stripes_composite_is_the_per_pixel_maximum():
    s, b = _scene(), 150.0
    h = _harness(chart_bright_roi=[4, 12, 8, 32], chart_dark_roi=[12, 24, 8, 32])
    comp = _scan(h, 7, "stripes", list(_stripe_frames(s, b, 8)), stripes=8)
    assert comp.method == "stripes" and comp.scan_id == 7
    np.testing.assert_allclose(comp.images["composite"], s + b)
    # Michelson contrast of the bars: (1350 - 550) / (1350 + 550)
    assert comp.metrics["contrast"] == pytest.approx(800.0 / 1900.0)
    assert comp.metrics["frames"] == 8 and comp.metrics["error_vs_truth"] is None
    assert h.published("medium/estimate") == []


def test_polarized_stripes_recover_s_and_p_with_either_angle_order():
    s, p, b = _scene(), 0.8, 1000.0
    e_b = [(img, pat, 30.2) for img, pat, _ in _stripe_frames(s / 2, b * (1 - p) / 2, 6)]
    e_w = [(img, pat, 119.9) for img, pat, _ in _stripe_frames(s / 2, b * (1 + p) / 2, 6)]
    h = _harness(object_free_roi=[0, 24, 0, 8])
    # the co-polarized angle comes first in the scan's list: the node must tell E_b from the light level
    comp = _scan(h, 3, "polarized_stripes", e_w + e_b, stripes=6, analyzer=[120.0, 30.0])
    assert comp.metrics["p"] == pytest.approx(p, abs=1e-3)
    # eq. 6: E_b (1 + 1/p) + E_w (1 - 1/p) = S wherever the stripe lit the pixel
    np.testing.assert_allclose(comp.images["composite"], s, atol=2.0)
    np.testing.assert_allclose(comp.images["e_b"], s / 2 + b * (1 - p) / 2, atol=0.5)
    est = h.published("medium/estimate")[-1]
    assert est.p == pytest.approx(p, abs=1e-3) and est.scan_id == 3


def test_polarized_flood_uses_eq6_with_p_from_the_object_free_region():
    s, p, b = _scene(), 0.6, 800.0
    frames = [(_dn(s / 2 + b * (1 - p) / 2), "flood", 0.0), (_dn(s / 2 + b * (1 + p) / 2), "flood", 90.0)]
    h = _harness(object_free_roi=[0, 24, 0, 8])
    comp = _scan(h, 1, "polarized_flood", frames, analyzer=[0.0, 90.0])
    assert comp.metrics["p"] == pytest.approx(p, abs=2e-3)
    np.testing.assert_allclose(comp.images["composite"], s, atol=3.0)


def test_flood_is_the_frame_above_the_dark_offset():
    s, b = _scene(), 300.0
    h = _harness()
    comp = _scan(h, 2, "flood", [(_dn(s + b), "flood", None)])
    np.testing.assert_allclose(comp.images["composite"], s + b)
    assert comp.metrics["contrast"] is None  # neither truth nor bar regions


def test_hf_separation_gives_the_direct_image():
    d = _scene()
    g = 500.0
    checker = ((np.arange(H)[:, None] // 4 + np.arange(W)[None, :] // 4) % 2).astype(float)
    frames = [(_dn(d * checker + g / 2), "checker:4:0", None),
              (_dn(d * (1 - checker) + g / 2), "checker:4:4", None)]
    h = _harness()
    comp = _scan(h, 4, "hf_separation", frames)
    np.testing.assert_allclose(comp.images["composite"], d, atol=1.0)
    np.testing.assert_allclose(comp.images["global"], g, atol=1.0)


def test_saturated_pixels_are_masked_not_mixed_in():
    s, b = _scene(), 100.0
    frames = list(_stripe_frames(s, b, 4))
    img = frames[2][0].copy()
    img[0, 20] = 4095  # full scale of 12 bits
    frames[2] = (img, frames[2][1], None)
    comp = _scan(_harness(), 5, "stripes", frames, stripes=4)
    assert comp.images["saturated"][0, 20] == 1 and comp.images["saturated"].sum() == 1
    assert comp.metrics["saturated_pixels"] == 1


def test_bad_and_mismatched_frames_are_dropped_and_counted():
    s, b = _scene(), 100.0
    h = _harness()
    good = list(_stripe_frames(s, b, 4))
    no_scan_yet = Frame(image=good[0][0], exposure_s=0.01, pattern="stripe:0/4", scan_id=9)
    h.deliver("camera/frame", no_scan_yet)
    h.deliver("emitter/scan", ScanEvent(scan_id=9, event="start", method="stripes", stripes=4))
    for step, (img, pat, _) in enumerate(good):
        h.deliver("camera/frame", Frame(image=img, exposure_s=0.01, pattern=pat, scan_id=9, step=step))
    bright = np.full((H, W), 4000, np.uint16)
    junk = [
        Frame(image=good[0][0], exposure_s=0.01, pattern="stripe:0/4", scan_id=8, step=9),  # another scan
        Frame(image=np.zeros((H, W + 1), np.uint16), exposure_s=0.01, pattern="stripe:0/4", scan_id=9,
              step=10),  # another shape
        Frame(image=good[0][0].astype(np.float32), exposure_s=0.01, pattern="stripe:0/4", scan_id=9,
              step=11),  # another dtype
        Frame(image=bright, exposure_s=0.01, pattern="stripe:1/4", scan_id=9, step=1),  # step seen
        Frame(image=bright, exposure_s=0.01, pattern="flood", scan_id=9, step=12),  # not a stripe
    ]
    for f in junk:
        h.deliver("camera/frame", f)
    h.deliver_raw("camera/frame", [b"not a message"])
    h.deliver("emitter/scan", ScanEvent(scan_id=9, event="done", method="stripes", stripes=4))
    c = h.node.counters
    assert (c["frames_unexpected"], c["frames_mismatched"], c["frames_bad"], c["frames_duplicate"],
            c["frames_bad_pattern"], c["bad"]) == (1, 1, 2, 1, 1, 1)
    comp = h.published("compositor/composite")[-1]
    np.testing.assert_allclose(comp.images["composite"], s + b)  # none of the junk got in
    assert comp.metrics["frames"] == 4 and comp.metrics["frames_dropped"] == 4


def test_a_polarized_frame_at_a_foreign_angle_is_dropped():
    s, b = _scene(), 100.0
    h = _harness(angle_tolerance_deg=1.0)
    frames = [(_dn(s + b), "flood", 0.0), (_dn(s + b), "flood", 45.0), (_dn(s + 2 * b), "flood", 90.4)]
    _scan(h, 1, "polarized_flood", frames, analyzer=[0.0, 90.0])
    assert h.node.counters["frames_bad_angle"] == 1


def test_memory_does_not_grow_with_the_number_of_stripes():
    s, b = _scene() * 0 + 10.0, 5.0
    big = (480, 640)

    def retained(n):
        h = _harness()
        h.deliver("emitter/scan", ScanEvent(scan_id=1, event="start", method="stripes", stripes=n))
        img = np.full(big, 100, np.uint16)
        h.deliver("camera/frame", Frame(image=img, exposure_s=0.01, pattern=f"stripe:0/{n}", scan_id=1))
        tracemalloc.start()
        before = tracemalloc.get_traced_memory()[0]
        for k in range(1, n):
            h.deliver("camera/frame", Frame(image=img, exposure_s=0.01, pattern=f"stripe:{k}/{n}", scan_id=1,
                                            step=k))
        grown = tracemalloc.get_traced_memory()[0] - before
        tracemalloc.stop()
        return grown

    frame_bytes = big[0] * big[1] * 2
    assert s.shape and b  # the scene is irrelevant here: only the buffers count
    assert retained(60) < frame_bytes / 4  # not one more frame kept, let alone 59
    assert retained(60) - retained(6) < frame_bytes / 8


def test_truth_gives_error_and_contrast_and_files_are_written(tmp_path):
    s, b = _scene(), 200.0
    band = np.full((H, W), -1, np.int32)
    band[:, 8:] = 0
    high = np.zeros((H, W), bool)
    high[4:12, 8:] = True
    h = _harness(out=str(tmp_path), use_truth=True, dark_offset_dn=None)
    truth = Composite(images={"S": s, "chart_band": band, "chart_high": high}, method="truth",
                      metrics={"dark_offset_dn": float(DARK)})
    h.on_call("simulator/truth", lambda req: truth)
    frames = [(_dn(s + b), "flood", None)]
    comp = _scan(h, 11, "flood", frames)
    # relative RMS after the least-squares gain g = <E, S>/<E, E>, computed plainly
    e = (s + b).ravel()
    g = (e @ s.ravel()) / (e @ e)
    expected_err = np.sqrt(np.sum((g * e - s.ravel()) ** 2)) / np.sqrt(np.sum(s ** 2))
    assert comp.metrics["error_vs_truth"] == pytest.approx(expected_err, rel=1e-6)
    assert comp.metrics["contrast"] == pytest.approx((1400.0 - 600.0) / (1400.0 + 600.0))
    _scan(h, 12, "stripes", list(_stripe_frames(s, 20.0, 4)), stripes=4)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert set(metrics) == {"flood", "stripes"}
    assert metrics["stripes"]["contrast"] > metrics["flood"]["contrast"]
    png = cv2.imread(str(tmp_path / "flood.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and png[0, 0] == 200 and png[5, 20] == 1400
    tif = cv2.imread(str(tmp_path / "stripes.tiff"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(tif, s + 20.0)
    assert (tmp_path / "comparison.png").stat().st_size > 1000
    # a restarted compositor keeps what metrics.json already holds
    h2 = _harness(out=str(tmp_path))
    assert set(h2.node.metrics) == {"flood", "stripes"}


def _truth_scan(h, scan_id, image, truth=None):
    """A flood scan during which the simulator publishes ``truth`` (after the start, as it does)."""
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="start", method="flood"))
    if truth is not None:
        h.deliver("simulator/truth", truth)
    h.deliver("camera/frame", Frame(image=image, exposure_s=0.01, pattern="flood", scan_id=scan_id, step=0))
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="done", method="flood"))
    return h.published("compositor/composite")[-1]


def test_truth_on_the_topic_is_taken_before_the_service():
    """A replay has no simulator: the truth recorded on the topic must score the scan as the service did."""
    s, b = _scene(), 200.0
    band = np.full((H, W), -1, np.int32)
    band[:, 8:] = 0
    high = np.zeros((H, W), bool)
    high[4:12, 8:] = True
    topic = Composite(images={"S": s, "chart_band": band, "chart_high": high}, method="truth",
                      metrics={"dark_offset_dn": float(DARK)})
    served = Composite(images={"S": 2 * s + 1, "chart_band": band, "chart_high": ~high}, method="truth",
                       metrics={"dark_offset_dn": 0.0})
    h = _harness(use_truth=True, dark_offset_dn=None)
    h.on_call("simulator/truth", lambda req: served)  # must not be asked while the scan has its message
    comp = _truth_scan(h, 3, _dn(s + b), topic)
    assert not h.bus.clients.get(h.full("simulator/truth"), type("c", (), {"requests": []})).requests
    assert comp.metrics["dark_offset_dn"] == DARK
    assert comp.metrics["contrast"] == pytest.approx((1400.0 - 600.0) / (1400.0 + 600.0))
    e = (s + b).ravel()
    g = (e @ s.ravel()) / (e @ e)
    expected_err = np.sqrt(np.sum((g * e - s.ravel()) ** 2)) / np.sqrt(np.sum(s ** 2))
    assert comp.metrics["error_vs_truth"] == pytest.approx(expected_err, rel=1e-6)
    # no message for this scan (the last one is another pose's): the service answers
    comp = _truth_scan(h, 4, _dn(s + b))
    assert comp.metrics["dark_offset_dn"] == 0.0 and comp.metrics["contrast"] < 0


def test_without_a_service_the_scans_truth_message_is_waited_for_once_the_topic_is_silent():
    s = _scene()
    truth = Composite(images={"S": s, "chart_band": np.zeros((H, W), np.int32),
                              "chart_high": np.zeros((H, W), bool)}, method="truth",
                      metrics={"dark_offset_dn": float(DARK)})
    h = _harness(use_truth=True, dark_offset_dn=None, truth_wait_s=0.5)
    h.node._truth_served = False  # as when no node serves simulator/truth (a replay)
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="start", method="flood"))
    h.deliver("camera/frame", Frame(image=_dn(s), exposure_s=0.01, pattern="flood", scan_id=1, step=0))
    h.queue("simulator/truth", truth)  # trails the frame: taken while waiting, not dispatched yet
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="done", method="flood"))
    assert h.published("compositor/composite")[-1].metrics["dark_offset_dn"] == DARK
    t0 = h.bus.now()
    comp = _truth_scan(h, 2, _dn(s))  # no message: waited for (the topic has spoken before), then none
    assert comp.metrics["dark_offset_dn"] == 0.0 and h.bus.now() - t0 >= 0.5
    h2 = _harness(use_truth=True, dark_offset_dn=None, truth_wait_s=0.5)
    h2.node._truth_served = False
    _truth_scan(h2, 1, _dn(s))
    t0 = h2.bus.now()
    _truth_scan(h2, 2, _dn(s))  # a silent topic is not waited for again
    assert h2.bus.now() - t0 < 0.5


def test_a_fault_ends_the_scan_without_a_composite():
    h = _harness()
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="start", method="stripes", stripes=2))
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="fault", method="stripes", detail="frame timeout"))
    assert h.published("compositor/composite") == [] and h.node.counters["scans_failed"] == 1
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="done", method="stripes"))
    assert h.published("compositor/composite") == []


def test_a_scan_without_usable_frames_publishes_a_failed_composite_at_once():
    h = _harness()
    h.deliver("emitter/scan", ScanEvent(scan_id=6, event="start", method="flood"))
    h.deliver("emitter/scan", ScanEvent(scan_id=6, event="done", method="flood"))
    comp = h.published("compositor/composite")[-1]
    assert comp.scan_id == 6 and comp.images == {} and "no frames" in comp.metrics["error"]
    assert h.node.counters["scans_failed"] == 1


def test_saturated_bars_give_no_contrast_rather_than_a_wrong_one():
    img = np.full((H, W), 4095, np.uint16)
    h = _harness(chart_bright_roi=[4, 12, 8, 32], chart_dark_roi=[12, 24, 8, 32])
    comp = _scan(h, 8, "flood", [(img, "flood", None)])
    assert comp.metrics["contrast"] is None and "saturated" in comp.metrics["metrics_error"]
    assert comp.images["saturated"].all()


def test_frames_ahead_of_their_start_event_are_kept():
    """Scan events and frames come from two publishers: a busy compositor may see a scan's first frames
    before its "start"; the pending start is taken first, so no frame is lost."""
    s, b = _scene(), 100.0
    h = _harness()
    h.queue("emitter/scan", ScanEvent(scan_id=4, event="start", method="stripes", stripes=4))
    for step, (img, pat, _) in enumerate(_stripe_frames(s, b, 4)):
        h.deliver("camera/frame", Frame(image=img, exposure_s=0.01, pattern=pat, scan_id=4, step=step))
    h.deliver("emitter/scan", ScanEvent(scan_id=4, event="done", method="stripes", stripes=4))
    comp = h.published("compositor/composite")[-1]
    assert comp.metrics["frames"] == 4 and h.node.counters["frames_unexpected"] == 0
    np.testing.assert_allclose(comp.images["composite"], s + b)


def test_the_polarizers_calibration_frames_are_ignored_quietly():

    h = _harness()
    h.deliver("camera/frame", Frame(image=np.zeros((H, W), np.uint16), exposure_s=0.01, pattern="flood",
                                    scan_id=CALIBRATION_SCAN_ID + 1))
    assert h.node.counters["frames_calibration"] == 1 and h.node.counters["frames_unexpected"] == 0
    assert not [text for level, text in h.logs if level == "WARNING"]
