"""The simulator node through the harness (and its hosted CiA 402 drive on a real zmq CAN segment).

Physics checks use identities that do not depend on the code under test: Malus' law (two crossed analyzer
frames add up to the frame without analyzer), the EMVA 1288 mean and variance, the camera–source distance
of a moved source, the DN level being independent of the resolution once the exposure follows the pixel
solid angle.
"""

import shutil
import tempfile

import numpy as np
import pytest
from polarstripe.msgs import Plan, RenderRequest, ScanEvent, SimFault
from polarstripe.nodes.simulator import Simulator
from polarstripe.nodes.simulator_frames import SimulatorError
from polarstripe.runtime.params import ParamError
from polarstripe.runtime.testing import NodeHarness
from polarstripe.sim.scene import load_scene


def sim(**params):
    return NodeHarness(Simulator, name="simulator", namespace="/rig",
                       params={"resolution": "48x36", "seed": 3, **params})


def dn(h, pattern="flood", analyzer=True, step=0):
    f = h.call("simulator/render", RenderRequest(pattern=pattern, analyzer=analyzer, step=step))
    return f, f.image.astype(float)


def truth(h, scan_id=1):
    """The ground truth the simulator publishes when scan ``scan_id`` starts."""
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="start", method="flood"))
    return h.published("simulator/truth")[-1]


def test_crossed_analyzer_frames_add_up_to_the_frame_without_analyzer():
    for angle in (0.0, 30.0):
        h = sim(analyzer_deg=angle)
        dark = truth(h).metrics["dark_offset_dn"]
        _, a = dn(h)
        h2 = sim(analyzer_deg=angle + 90.0)
        _, b = dn(h2)
        f, none = dn(h, analyzer=False)
        assert f.polarizer_deg is None
        # Malus: I(φ) + I(φ + 90°) = (k1 + k2)·(D + A + B) with k1 = 1, k2 = 1/1000 (the scene's extinction)
        lhs, rhs = (a - dark) + (b - dark), (1 + 1e-3) * (none - dark)
        assert abs(lhs.mean() / rhs.mean() - 1) < 0.01


def test_crossed_analyzer_passes_less_backscatter_than_parallel():
    # the source is polarized at 90 deg and backscatter keeps most of it: E_b is near 0 deg
    _, eb = dn(sim(analyzer_deg=0.0))
    _, ew = dn(sim(analyzer_deg=90.0))
    assert ew.mean() > 1.5 * eb.mean()


def test_second_angle_reuses_the_transport_and_a_moved_source_renders_again():
    h = sim()
    dn(h, "stripe:1/4")
    dn(h, "stripe:1/4", analyzer=False)
    assert h.node.stats["renders"] == 2  # flood (auto exposure) + the stripe once
    ack = h.call("simulator/move_source", Plan(modality="stripes", separation_m=0.3))
    assert ack.ok
    pos = np.array(h.node.scene.projector.position)
    assert np.linalg.norm(pos - np.array(h.node.scene.camera.position)) == pytest.approx(0.3, abs=1e-9)
    dn(h, "stripe:1/4")
    assert h.node.stats["renders"] == 4  # flood and stripe again at the new pose


def test_a_plan_on_the_topic_moves_the_source_too():
    h = sim()
    h.deliver("planner/plan", Plan(modality="flood", separation_m=0.25))
    assert h.node.scene.separation_m() == pytest.approx(0.25)


def test_a_plan_during_a_scan_waits_for_its_end():
    h = sim()
    h.deliver("emitter/scan", ScanEvent(scan_id=4, event="start", method="stripes"))
    h.deliver("planner/plan", Plan(modality="stripes", separation_m=0.3))
    assert h.node.scene.separation_m() == pytest.approx(0.2)  # not in the middle of scan 4
    h.deliver("emitter/scan", ScanEvent(scan_id=4, event="fault", method="stripes", detail="x"))
    assert h.node.scene.separation_m() == pytest.approx(0.3)


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan")])
def test_bad_separation_is_refused_and_the_source_stays(bad):
    h = sim()
    before = h.node.scene.projector.position
    ack = h.call("simulator/move_source", Plan(modality="stripes", separation_m=bad))
    assert not ack.ok and "separation_m" in ack.detail
    assert h.node.scene.projector.position == before


def test_dn_level_does_not_depend_on_the_resolution():
    # exposure ∝ pixel solid angle ∝ 1/w²: the same radiance gives the same mean electrons per pixel
    small, big = (sim(resolution=r, auto_exposure=False) for r in ("40x30", "80x60"))
    _, a = dn(small, analyzer=False)
    _, b = dn(big, analyzer=False)
    assert abs(a.mean() / b.mean() - 1) < 0.03


def test_auto_exposure_keeps_a_near_source_flood_off_the_rails():
    h = sim()
    h.call("simulator/move_source", Plan(modality="flood", separation_m=0.02))  # huge backscatter
    f, none = dn(h, analyzer=False)
    assert f.exposure_s < load_scene(None).camera.exposure_s * (48 / 640) ** 2
    assert (f.image >= 4095).mean() < 0.01
    h2 = sim(auto_exposure=False)
    h2.call("simulator/move_source", Plan(modality="flood", separation_m=0.02))
    assert (dn(h2, analyzer=False)[0].image >= 4095).mean() > 0.5  # without it, the flood clips


def test_model_at_lower_resolution_matches_the_full_render_on_average():
    full = sim(resolution="96x72", render_scale=1)
    half = sim(resolution="96x72", render_scale=2)
    _, a = dn(full, "stripe:2/4")
    _, b = dn(half, "stripe:2/4")
    assert b.shape == a.shape == (72, 96)
    assert abs(b.mean() / a.mean() - 1) < 0.05


def test_truth_marks_the_chart_and_its_bars():
    h = sim()
    t = truth(h, scan_id=5)
    assert t.scan_id == 5
    s, band, high = t.images["S"], t.images["chart_band"], t.images["chart_high"]
    assert s.shape == band.shape == high.shape == (36, 48) and s.dtype == np.float64
    on = band >= 0
    assert 0.1 < on.mean() < 0.9 and not high[~on].any()
    assert s[on & high].mean() > s[on & ~high].mean() > 0


def test_truth_is_the_unscattered_chart_not_the_blurred_one_the_water_shows():
    """docs/physics.md §10.8: S is the unscattered object radiance, so band 0's bars (albedo 0.6 and 0.06)
    keep their Michelson contrast 0.818, while the flood frame through the water has lost most of it."""
    h = sim()
    t = truth(h)
    s, band, high = t.images["S"], t.images["chart_band"], t.images["chart_high"]
    b0 = band == 0
    c_truth = (s[b0 & high].mean() - s[b0 & ~high].mean()) / (s[b0 & high].mean() + s[b0 & ~high].mean())
    assert abs(c_truth - 0.818) < 0.03
    _, frame = dn(h, analyzer=False)
    frame = frame - t.metrics["dark_offset_dn"]
    c_frame = (frame[b0 & high].mean() - frame[b0 & ~high].mean()) / (
        frame[b0 & high].mean() + frame[b0 & ~high].mean())
    assert c_frame < 0.5 * c_truth


def test_truth_is_published_at_every_scan_start_for_the_pose_of_that_scan():
    h = sim()
    served = h.node.truth()
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="start", method="flood"))
    h.deliver("emitter/scan", ScanEvent(scan_id=1, event="done", method="flood"))
    h.deliver("emitter/scan", ScanEvent(scan_id=2, event="start", method="stripes"))  # the latch again
    first, again = h.published("simulator/truth")
    for t in (first, again):
        assert t.method == "truth" and set(t.images) == set(served.images)
        assert all(np.array_equal(t.images[k], served.images[k]) for k in served.images)
        assert t.metrics == served.metrics
    h.deliver("emitter/scan", ScanEvent(scan_id=2, event="done", method="stripes"))
    assert h.call("simulator/move_source", Plan(modality="flood", separation_m=0.3)).ok
    h.deliver("emitter/scan", ScanEvent(scan_id=3, event="start", method="flood"))
    moved = h.published("simulator/truth")[-1]
    assert len(h.published("simulator/truth")) == 3
    assert [t.scan_id for t in h.published("simulator/truth")] == [1, 2, 3]  # each names its scan
    assert moved.metrics["separation_m"] == pytest.approx(0.3) and served.metrics["separation_m"] != 0.3


def test_faults_and_bad_requests_are_clear():
    h = sim()
    assert h.call("simulator/fault", SimFault(command="camera_lost on")).ok
    with pytest.raises(SimulatorError, match="camera lost"):
        h.node.render(RenderRequest(pattern="flood"))
    h.call("simulator/fault", SimFault(command="camera_lost off"))
    ack = h.call("simulator/fault", SimFault(command="explode"))
    assert not ack.ok and "unknown fault command 'explode'" in ack.detail and "never_settle" in ack.detail
    ack = h.call("simulator/fault", SimFault(command="never_settle on"))
    assert not ack.ok and "can_channel" in ack.detail  # no drive hosted
    with pytest.raises(SimulatorError, match="pattern 'stripe:9/4'"):
        h.node.render(RenderRequest(pattern="stripe:9/4"))
    with pytest.raises(SimulatorError, match="param 'faults'"):
        sim(faults=["bogus"])


@pytest.mark.parametrize("command, why", [
    ("position_limit 5", "position_limit takes 2 numbers: position_limit MIN MAX"),
    ("bus_off", "bus_off takes 1 number: bus_off SECONDS"),
    ("bus_off 1e12", "bus_off 1e12: seconds must be in [0, 3600]"),
    ("frame_delay -1", "frame_delay -1: seconds must be in [0, 3600]"),
    ("bus_off soon", "could not convert string to float: 'soon'"),
])
def test_a_bad_fault_argument_is_one_clear_refusal(command, why):
    ack = sim().call("simulator/fault", SimFault(command=command))
    assert not ack.ok and why in ack.detail, ack.detail


@pytest.mark.parametrize("params, why", [
    ({"fidelity": "ultra"}, "params: fidelity 'ultra' is not preview, standard, reference"),
    ({"resolution": "100000x100000"}, "params: resolution 100000x100000 is 1e\\+04 Mpx, beyond the limit"),
    ({"threads": -1}, "threads must be >= 0"),
    ({"mosaic_crosstalk": [0.1]}, "mosaic_crosstalk must be \\[edge, diagonal\\]"),
    ({"mosaic_extinction_ratio": 0.5}, "extinction_ratio=0.5 must be > 1"),
    ({"mosaic_layout": [0, 45, 90, 90]}, "mosaic layout"),
])
def test_bad_params_are_refused_before_anything_starts(params, why):
    with pytest.raises(ParamError, match=why):
        sim(**params)


def test_off_pattern_is_a_dark_frame():
    _, img = dn(sim(), "off")
    assert abs(img.mean() - 64) < 1  # the dark offset (64 DN by default)


def test_the_analyzer_follows_the_hosted_drive():
    from polarstripe.nodes.drivers.cia402 import Cia402Stage

    folder = tempfile.mkdtemp(prefix="ps-can-", dir="/tmp")
    channel = f"ipc://{folder}/bus"
    h = sim(can_channel=channel)
    try:
        with Cia402Stage(channel, interface="zmq") as stage:
            stage.move_to(37.5)
            stage.wait_settled(5.0)
            f, _ = dn(h)
            assert f.polarizer_deg == pytest.approx(37.5, abs=0.01)
    finally:
        h.stop()
        shutil.rmtree(folder, ignore_errors=True)


def test_the_analyzer_follows_the_hosted_ell14_through_its_link(tmp_path):
    from polarstripe.nodes.drivers.ell14 import Ell14Stage

    link = tmp_path / "ell14"
    h = sim(ell14_link=str(link))
    try:
        assert link.is_symlink()
        with Ell14Stage(str(link)) as stage:
            stage.move_to(45.0)
            stage.wait_settled(5.0)
            f, _ = dn(h)
            assert f.polarizer_deg == pytest.approx(45.0, abs=0.01)
    finally:
        h.stop()
    assert not link.exists()  # removed on the way out


def test_a_mosaic_frame_is_malus_per_pixel_its_0_and_90_deg_pixels_add_up_to_no_analyzer():
    """simulator/render_mosaic: each pixel through its own micro-polarizer (90, 45 / 135, 0 deg); a 0 and a
    90 deg pixel of one 2x2 cell add up to (1 + 1/ER) times the frame without analyzer there (Malus), and
    so do the 45 and 135 deg ones; crosstalk moves light between them, not out."""
    h = sim(resolution="48x36")
    dark = truth(h).metrics["dark_offset_dn"]
    f = h.call("simulator/render_mosaic", RenderRequest(pattern="flood"))
    assert f.mosaic_deg == [90.0, 45.0, 135.0, 0.0] and f.polarizer_deg is None
    _, none = dn(h, analyzer=False)
    raw = f.image.astype(float) - dark
    cells = (none - dark).reshape(18, 2, 24, 2).mean(axis=(1, 3))
    pair_0_90 = raw[0::2, 0::2] + raw[1::2, 1::2]
    pair_45_135 = raw[0::2, 1::2] + raw[1::2, 0::2]
    for pair in (pair_0_90, pair_45_135):
        assert pair.mean() / cells.mean() == pytest.approx(1 + 1 / 300, rel=0.01)
    # the source is polarized near 90 deg after backscatter: the 0 deg pixels (crossed) are the darker
    assert raw[1::2, 1::2].mean() < 0.8 * raw[0::2, 0::2].mean()
