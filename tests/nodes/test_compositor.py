"""The compositor node through the harness on synthetic frames whose composites are known in closed form.

Scenes are built so the answer is exact: a stripe lights each column block once over a constant backscatter
(max composite = S + b); polarized frames follow eqs. 4-5 with S = 0 in an object-free region (p and S come
back exactly); complementary checkers give L+ = D + G/2, L- = G/2 (direct = D).
"""

from __future__ import annotations

import dataclasses
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


def _scan(h, scan_id, method, frames, *, stripes=0, analyzer=(), truth=None):
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="start", method=method, stripes=stripes,
                                        analyzer_deg=list(analyzer)))
    if truth is not None:  # as the simulator publishes it, after the start
        h.deliver("simulator/truth", dataclasses.replace(truth, scan_id=scan_id))
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
    assert h.published("compositor/medium_p") == []


def test_polarized_stripes_recover_s_and_p_with_either_angle_order():
    s, p, b = _scene(), 0.8, 1000.0
    e_b = [(img, pat, 30.2) for img, pat, _ in _stripe_frames(s / 2, b * (1 - p) / 2, 6)]
    e_w = [(img, pat, 119.9) for img, pat, _ in _stripe_frames(s / 2, b * (1 + p) / 2, 6)]
    h = _harness(object_free_roi=[0, 24, 0, 8])
    # the co-polarized angle comes first in the scan's list: the node must tell E_b from the light level
    comp = _scan(h, 3, "polarized_stripes", e_w + e_b, stripes=6, analyzer=[120.0, 30.0])
    assert comp.metrics["p"] == pytest.approx(p, abs=1e-3)
    assert comp.metrics["p_backscatter"] == pytest.approx(p, abs=2e-3)  # no object light there: the same
    # eq. 6: E_b (1 + 1/p) + E_w (1 - 1/p) = S wherever the stripe lit the pixel
    np.testing.assert_allclose(comp.images["composite"], s, atol=2.0)
    np.testing.assert_allclose(comp.images["e_b"], s / 2 + b * (1 - p) / 2, atol=0.5)
    est = h.published("compositor/medium_p")[-1]
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
    # a frame of a scan whose start never comes: held, then dropped when a later scan starts
    no_scan_yet = Frame(image=good[0][0], exposure_s=0.01, pattern="stripe:0/4", scan_id=8)
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
    frames = [(_dn(s + b), "flood", None)]
    comp = _scan(h, 11, "flood", frames, truth=truth)
    # relative RMS after the least-squares gain g = <E, S>/<E, E>, computed plainly
    e = (s + b).ravel()
    g = (e @ s.ravel()) / (e @ e)
    expected_err = np.sqrt(np.sum((g * e - s.ravel()) ** 2)) / np.sqrt(np.sum(s ** 2))
    assert comp.metrics["error_vs_truth"] == pytest.approx(expected_err, rel=1e-6)
    assert comp.metrics["contrast"] == pytest.approx((1400.0 - 600.0) / (1400.0 + 600.0))
    _scan(h, 12, "stripes", list(_stripe_frames(s, 20.0, 4)), stripes=4, truth=truth)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert set(metrics) == {"flood", "stripes"}
    assert metrics["stripes"]["contrast"] > metrics["flood"]["contrast"]
    png = cv2.imread(str(tmp_path / "flood.png"), cv2.IMREAD_UNCHANGED)  # for people: 8 bits, stretched
    assert png.dtype == np.uint8 and png.shape == (H, W) and int(png[5, 20]) > int(png[0, 0])
    flood = cv2.imread(str(tmp_path / "flood.tiff"), cv2.IMREAD_UNCHANGED)  # for analysis: DN as measured
    assert flood[0, 0] == 200 and flood[5, 20] == 1400
    tif = cv2.imread(str(tmp_path / "stripes.tiff"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(tif, s + 20.0)
    assert (tmp_path / "comparison.png").stat().st_size > 1000
    # a restarted compositor keeps what metrics.json already holds
    h2 = _harness(out=str(tmp_path))
    assert set(h2.node.metrics) == {"flood", "stripes"}


def _truth(s, dark=float(DARK), high=None):
    band = np.full((H, W), -1, np.int32)
    band[:, 8:] = 0
    if high is None:
        high = np.zeros((H, W), bool)
        high[4:12, 8:] = True
    return Composite(images={"S": s, "chart_band": band, "chart_high": high}, method="truth",
                     metrics={"dark_offset_dn": dark})


def _truth_scan(h, scan_id, image, truth=None):
    """A flood scan during which the simulator publishes ``truth`` (after the start, as it does)."""
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="start", method="flood"))
    if truth is not None:
        h.deliver("simulator/truth", truth)
    h.deliver("camera/frame", Frame(image=image, exposure_s=0.01, pattern="flood", scan_id=scan_id, step=0))
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="done", method="flood"))
    return h.published("compositor/composite")


def test_a_scan_is_scored_against_its_own_truth_message_only():
    """The truth comes one way, on the topic, naming its scan: another scan's truth is never used; without
    its own the scan waits ``truth_wait_s`` (a timer), then is composited without an error vs truth."""
    s, b = _scene(), 200.0
    h = _harness(use_truth=True, dark_offset_dn=None, truth_wait_s=0.5)
    comp = _truth_scan(h, 3, _dn(s + b), dataclasses.replace(_truth(s), scan_id=3))[-1]
    assert comp.metrics["dark_offset_dn"] == DARK
    assert comp.metrics["contrast"] == pytest.approx((1400.0 - 600.0) / (1400.0 + 600.0))
    e = (s + b).ravel()
    g = (e @ s.ravel()) / (e @ e)
    expected_err = np.sqrt(np.sum((g * e - s.ravel()) ** 2)) / np.sqrt(np.sum(s ** 2))
    assert comp.metrics["error_vs_truth"] == pytest.approx(expected_err, rel=1e-6)
    # scan 4 hears only the truth of scan 9 (another pose's): held for its own, then scored without
    other = dataclasses.replace(_truth(2 * s + 1, dark=0.0), scan_id=9)
    assert len(_truth_scan(h, 4, _dn(s + b), other)) == 1  # not yet
    h.advance(0.49)
    assert len(h.published("compositor/composite")) == 1
    h.advance(0.02)
    comp = h.published("compositor/composite")[-1]
    assert comp.scan_id == 4 and comp.metrics["dark_offset_dn"] == 0.0
    assert comp.metrics["error_vs_truth"] is None and comp.metrics["contrast"] is None
    assert any("scan 4" in text and "no ground truth" in text for _, text in h.logs)
    assert not h.bus.clients  # nobody is asked: no service call toward the simulator


def test_a_truth_that_trails_the_frames_is_still_taken_and_a_silent_topic_is_not_waited_for():
    s = _scene()
    truth = dataclasses.replace(_truth(s), scan_id=1)
    h = _harness(use_truth=True, dark_offset_dn=None, truth_wait_s=0.5)
    assert _truth_scan(h, 1, _dn(s)) == []  # done and every frame in, but no truth yet: held
    h.advance(0.3)
    h.deliver("simulator/truth", truth)  # a replay: it trails the frames on its own socket
    comp = h.published("compositor/composite")[-1]
    assert comp.metrics["dark_offset_dn"] == DARK and comp.metrics["error_vs_truth"] is not None
    h.advance(1.0)
    assert len(h.published("compositor/composite")) == 1  # the cancelled timer did not finish it twice
    # a truth that came before its scan's start (another publisher) is kept for it
    h.deliver("simulator/truth", dataclasses.replace(truth, scan_id=2))
    assert _truth_scan(h, 2, _dn(s))[-1].metrics["dark_offset_dn"] == DARK
    h2 = _harness(use_truth=True, dark_offset_dn=None, truth_wait_s=0.5)
    assert _truth_scan(h2, 1, _dn(s)) == []
    h2.advance(0.5)
    assert h2.published("compositor/composite")[-1].metrics["dark_offset_dn"] == 0.0
    assert any("not waited for again" in text for _, text in h2.logs)
    assert len(_truth_scan(h2, 2, _dn(s))) == 2  # a silent topic is not waited for again: at once


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
    h.advance(0.05)  # the grace for frames in flight
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
    before its "start"; they are held and folded in when the start comes, so no frame is lost."""
    s, b = _scene(), 100.0
    h = _harness()
    for step, (img, pat, _) in enumerate(_stripe_frames(s, b, 4)):
        h.deliver("camera/frame", Frame(image=img, exposure_s=0.01, pattern=pat, scan_id=4, step=step))
    h.deliver("emitter/scan", ScanEvent(scan_id=4, event="start", method="stripes", stripes=4))
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


def test_frames_held_ahead_of_their_start_are_bounded():
    s, b = _scene(), 100.0
    h = _harness(early_frames=2)
    for step, (img, pat, _) in enumerate(_stripe_frames(s, b, 4)):
        h.deliver("camera/frame", Frame(image=img, exposure_s=0.01, pattern=pat, scan_id=4, step=step))
    assert h.node.counters["frames_unexpected"] == 2 and len(h.node.early) == 2  # steps 0 and 1 let go
    h.deliver("emitter/scan", ScanEvent(scan_id=4, event="start", method="stripes", stripes=4))
    assert h.node.scan.steps == {2, 3}


def test_the_scan_ends_when_done_and_its_last_frame_are_in_whichever_comes_last():
    s, b = _scene(), 100.0
    frames = [Frame(image=img, exposure_s=0.01, pattern=pat, scan_id=2, step=k)
              for k, (img, pat, _) in enumerate(_stripe_frames(s, b, 4))]
    h = _harness()
    h.deliver("emitter/scan", ScanEvent(scan_id=2, event="start", method="stripes", stripes=4))
    for f in frames[:3]:
        h.deliver("camera/frame", f)
    h.deliver("emitter/scan", ScanEvent(scan_id=2, event="done", method="stripes", stripes=4))
    assert h.published("compositor/composite") == []  # 3 of 4: the fourth is in flight
    h.advance(0.04)
    h.deliver("camera/frame", frames[3])  # within the grace: complete, at once
    comp = h.published("compositor/composite")[-1]
    assert comp.metrics["frames"] == 4 and "fault" not in comp.metrics
    np.testing.assert_allclose(comp.images["composite"], s + b)


def test_frames_missing_at_the_deadline_are_a_fault_n_of_m():
    s, b = _scene(), 100.0
    h = _harness(done_grace_s=0.2)
    event = dict(scan_id=5, method="polarized_stripes", stripes=4, analyzer_deg=[0.0, 90.0])
    h.deliver("emitter/scan", ScanEvent(event="start", **event))
    for k, (img, pat, _) in enumerate(list(_stripe_frames(s, b, 4))[:2]):
        h.deliver("camera/frame", Frame(image=img, exposure_s=0.01, pattern=pat, polarizer_deg=0.0, scan_id=5,
                                        step=k))
    h.deliver("emitter/scan", ScanEvent(event="done", **event))
    assert h.published("compositor/composite") == []
    h.advance(0.19)
    assert h.published("compositor/composite") == []
    h.advance(0.02)
    comp = h.published("compositor/composite")[-1]
    assert comp.metrics["fault"] == "2 of 8 frames"  # 4 stripes at 2 angles
    assert any(level == "WARNING" and "scan 5: 2 of 8 frames" in text for level, text in h.logs)
    assert "error" in comp.metrics and "two analyzer angles" in comp.metrics["error"]  # only one came


def test_a_new_start_waits_for_the_last_frames_of_a_scan_that_is_done():
    """Frames and scan events come on separate sockets, so under load the next scan's start can overtake the
    last frames of a scan that is done: the start is held and those frames still count."""
    s, b = _scene(), 100.0
    frames = [Frame(image=img, exposure_s=0.01, pattern=pat, scan_id=1, step=k)
              for k, (img, pat, _) in enumerate(_stripe_frames(s, b, 4))]
    h = _harness(done_grace_s=0.2)
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="start", method="stripes", stripes=4))
    h.deliver("camera/frame", frames[0])
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="done", method="stripes", stripes=4))
    h.deliver("emitter/scan", ScanEvent(scan_id=2, event="start", method="flood"))
    assert h.published("compositor/composite") == [] and h.node.scan.scan_id == 1  # held
    for f in frames[1:]:
        h.deliver("camera/frame", f)
    comp = h.published("compositor/composite")[-1]
    assert comp.scan_id == 1 and comp.metrics["frames"] == 4 and "fault" not in comp.metrics
    np.testing.assert_allclose(comp.images["composite"], s + b)
    assert h.node.scan.scan_id == 2 and h.node.scan.method == "flood"


def test_a_held_start_goes_at_the_deadline_or_with_a_frame_of_its_scan():
    s, b = _scene(), 100.0
    h = _harness(done_grace_s=0.2)
    for first in (1, 3):
        h.deliver("emitter/scan", ScanEvent(scan_id=first, event="start", method="stripes", stripes=4))
        h.deliver("camera/frame", Frame(image=_dn(s + b), exposure_s=0.01, pattern="stripe:0/4",
                                        scan_id=first))
        h.deliver("emitter/scan", ScanEvent(scan_id=first, event="done", method="stripes", stripes=4))
        h.deliver("emitter/scan", ScanEvent(scan_id=first + 1, event="start", method="flood"))
        if first == 1:  # nothing more comes: the frames deadline ends scan 1, then scan 2 starts
            h.advance(0.25)
        else:  # a frame of scan 4 comes after all of scan 3's: scan 3 ends at once, scan 4 takes the frame
            h.deliver("camera/frame", Frame(image=_dn(s + b), exposure_s=0.01, pattern="flood",
                                            scan_id=4))
        comp = h.published("compositor/composite")[-1]
        assert comp.scan_id == first and comp.metrics["fault"] == "1 of 4 frames"
        np.testing.assert_allclose(comp.images["composite"], s + b)
        assert h.node.scan.scan_id == first + 1
        h.deliver("emitter/scan", ScanEvent(scan_id=first + 1, event="done", method="flood"))
    last = h.published("compositor/composite")[-1]
    assert last.scan_id == 4 and last.metrics["frames"] == 1 and "fault" not in last.metrics
