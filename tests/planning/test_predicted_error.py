"""The error measure (planning/predicted_error.py) against closed forms, and the planner on it."""

import math

import numpy as np
import pytest
from polarstripe.planning.image_model import PLAN_FIDELITY, ImageModel
from polarstripe.planning.objectives import IDEAL_SENSOR, Samples, objective
from polarstripe.planning.planner import plan, plan_model
from polarstripe.planning.predicted_error import DRAW_BLOCK, composite, expected_error, reading_error
from polarstripe.sim.scene import SceneError, load_scene


def _chart(n=4000, r=0.4):
    """T of mean 1 and relative standard deviation r (two values, 1 ± r)."""
    return np.where(np.arange(n) % 2 == 0, 1.0 + r, 1.0 - r)


@pytest.mark.parametrize("r,b,nu", [(0.4, 0.0, 0.0), (0.4, 0.5, 0.0), (0.2, 3.0, 0.0), (0.4, 0.5, 0.1),
                                    (0.3, 0.0, 0.2)])
def test_offset_and_noise_match_the_closed_form(r, b, nu):
    """A uniform veil b (relative to the mean signal) and noise of relative variance ν² on T = 1 ± r:
    e² = [r²b² + (1 + r²)ν²] / [(1 + r²)((1 + b)² + r² + ν²)] (the gain-fitted error, derived by hand)."""
    t = _chart(r=r)
    got = expected_error(t + b, np.full(t.size, nu * nu), t, np.ones(t.size, bool))
    r2 = r * r
    want = math.sqrt((r2 * b * b + (1 + r2) * nu * nu) / ((1 + r2) * ((1 + b) ** 2 + r2 + nu * nu)))
    assert got == pytest.approx(want, rel=1e-9)


def test_error_limits():
    t = _chart()
    valid = np.ones(t.size, bool)
    assert expected_error(3.0 * t, np.zeros(t.size), t, valid) == pytest.approx(0.0, abs=1e-7)   # gain only
    assert expected_error(t, np.zeros(t.size), t, np.zeros(t.size, bool)) == 1.0     # all saturated
    big = expected_error(t + 1e9, np.zeros(t.size), t, valid)          # a veil without end: the chart's
    assert big == pytest.approx(0.4 / math.sqrt(1 + 0.16), rel=1e-6)  # angle to a constant, r/√(1 + r²)


@pytest.mark.parametrize("n", [20000, 2 * DRAW_BLOCK + 7])   # wider frames reuse a block of draws
def test_eq7_maximum_of_noisy_dark_frames(n):
    """Two frames of equal mean and unit variance: the maximum's mean is 1/√π above it (E max of two
    standard normals), its variance 1 − 1/π."""
    m, v = composite(np.full((2, n), 5.0), np.ones((2, n)))
    assert m.mean() == pytest.approx(5.0 + 1 / math.sqrt(math.pi), abs=0.01)
    assert v.mean() == pytest.approx(1 - 1 / math.pi, abs=0.02)
    one_m, one_v = composite(np.array([[1.0, 2.0]]), np.array([[0.5, 0.5]]))
    assert list(one_m) == [1.0, 2.0] and list(one_v) == [0.5, 0.5]


def test_eq6_removes_a_uniformly_polarized_veil_but_not_a_varying_one():
    """One median p̂ (half the pixels see no object, T = S = 0: p̂ is read there, as the compositor reads
    it) removes a uniformly polarized veil, not a varying one; the map removes both."""
    t = np.concatenate([_chart(), np.zeros(4000)])
    s, b = 1000.0 * t, np.full(t.size, 3000.0)
    kw = dict(full_well_e=math.inf, noise=False)
    chi = np.zeros(t.size)
    ramp = np.linspace(0.5, 0.9, t.size)
    uniform = reading_error("S_hat", s, b, np.full(t.size, 0.7), chi, t, p_rule="median", **kw)[0]
    varying = reading_error("S_hat", s, b, ramp, chi, t, p_rule="median", **kw)[0]
    mapped = reading_error("S_hat", s, b, ramp, chi, t, p_rule="map", **kw)[0]
    e_b = reading_error("E_b", s, b, np.full(t.size, 0.7), chi, t, **kw)[0]
    assert uniform == pytest.approx(0.0, abs=1e-6)        # Ŝ = S: no longer 1 by construction, but exact
    assert varying > 0.05 and e_b > 0.05                  # p ≠ p̂ somewhere; E_b keeps B(1 − p)/2
    assert mapped == pytest.approx(0.0, abs=1e-6)         # p̂(x) = p(x): Ŝ = S at every pixel
    noisy = reading_error("S_hat", s, b, np.full(t.size, 0.7), chi, t, full_well_e=math.inf)[0]
    assert noisy > 0.0                                    # eq. 6's noise is charged


def test_a_memo_shares_the_analyzer_frames_between_e_b_and_s_hat():
    """The planner hands the readings of one separation one memo: E_b's and Ŝ's errors through it are those
    made without it (a uniform veil of p 0.7 under a chart: Ŝ removes it, E_b keeps B(1 − p)/2)."""
    t = np.concatenate([_chart(), np.zeros(4000)])
    s, b, p, chi = np.stack([1000.0 * t] * 3), np.full((3, t.size), 3000.0), np.full((3, t.size), 0.7), \
        np.zeros((3, t.size))
    kw = dict(full_well_e=math.inf, read_noise_e=5.0)
    memo = {}
    shared = [reading_error(r, s, b, p, chi, t, memo=memo, **kw) for r in ("E_b", "S_hat", "E")]
    alone = [reading_error(r, s, b, p, chi, t, **kw) for r in ("E_b", "S_hat", "E")]
    assert shared == alone and set(memo) == {"analyzer"}
    assert alone[0][0] > 0.05 and alone[1][0] < alone[0][0]


def test_eq6_map_noise_gain_per_pixel_matches_the_closed_form():
    """The map rule on a chart T = 1 ± r under a veil B with p(x) in two halves: Ŝ = S, so the error is the
    noise alone, e² = V / (s² Σ T² + V) with V = Σ (1 + 1/p)² E_b + (1 − 1/p)² E_w (shot noise, E_b,w =
    ½(S + B(1 ∓ p))): hand-derived, each pixel with its own p."""
    r, s0, b0 = 0.4, 400.0, 900.0
    t = _chart(r=r)
    p = np.where(np.arange(t.size) < t.size // 2, 0.3, 0.8)
    s, b = s0 * t, np.full(t.size, b0)
    got = reading_error("S_hat", s, b, p, np.zeros(t.size), t, full_well_e=math.inf, p_rule="map")[0]
    e_b, e_w = 0.5 * (s + b * (1 - p)), 0.5 * (s + b * (1 + p))
    v = float(np.sum((1 + 1 / p) ** 2 * e_b + (1 - 1 / p) ** 2 * e_w))
    want = math.sqrt(v / (s0 ** 2 * t.size * (1 + r * r) + v))
    assert got == pytest.approx(want, rel=1e-9)
    one = reading_error("S_hat", s, b, p, np.zeros(t.size), t, full_well_e=math.inf, p_rule="median")[0]
    assert one > got                                      # one p̂ leaves half the veil (p ≠ p̂ there)


def test_a_stripe_composite_divided_by_the_flood_map_keeps_its_own_residual():
    """The map is the flood's (the compositor fits it to the flood pair): a frame whose backscatter has DOP
    p_s ≠ p_f keeps the veil B(1 − p_s/p_f), the closed form of the uniform veil b = (B/s)(1 − p_s/p_f)."""
    r, s0, b0, p_s, p_f = 0.4, 1000.0, 2000.0, 0.4, 0.6
    t = _chart(r=r)
    n = t.size
    flood = (np.full(n, 1.0), np.full(n, p_f), np.zeros(n))
    got = reading_error("S_hat", s0 * t, np.full(n, b0), np.full(n, p_s), np.zeros(n), t,
                        full_well_e=math.inf, noise=False, p_rule="map", flood_dop=flood)[0]
    b = b0 / s0 * (1 - p_s / p_f)
    r2 = r * r
    assert got == pytest.approx(math.sqrt(r2 * b * b / ((1 + r2) * ((1 + b) ** 2 + r2))), rel=1e-9)
    own = reading_error("S_hat", s0 * t, np.full(n, b0), np.full(n, p_s), np.zeros(n), t,
                        full_well_e=math.inf, noise=False, p_rule="map")[0]
    assert own == pytest.approx(0.0, abs=1e-7)            # its own DOP as the map: removed


def test_every_location_is_scored_through_the_one_analyzer_calibrated_on_the_whole_frame():
    """Two locations whose backscatter (p = 1) is polarized at 0 and at θ: the rig calibrates one analyzer on
    the whole flood, at χ̄ = θ/2, so each location's E_b keeps the veil c = ½B(1 − cos θ) over ½S (an analyzer
    per location would remove it: error 0); with the gain fitted on S = 1 ± r, by hand,
    e² = 1 − ((1 + r²)/2 + c)² / (((1 + r²)/4 + c + c²)(1 + r²))."""
    r, theta, b0 = 0.4, 0.8, 0.3
    t = _chart(r=r)
    n = t.size
    group = (np.arange(n) >= n // 2).astype(np.int64)
    chi = np.where(group == 0, 0.0, theta)
    b, p = np.full(n, b0), np.ones(n)
    samples = Samples(t, np.zeros(n), b, p, chi=chi, truth=t, group=group, flood_dop=(b, p, chi))
    obj = objective(samples, IDEAL_SENSOR, modality="stripes", reading="E_b", measure="error")
    c, q = 0.5 * b0 * (1 - math.cos(theta)), 1 + r * r
    want = math.sqrt(1 - (q / 2 + c) ** 2 / ((q / 4 + c + c * c) * q))
    assert obj.quality == pytest.approx([1 - want, 1 - want], rel=1e-9)
    assert obj.frame_quality == pytest.approx(1 - want, rel=1e-9)


def test_saturated_pixels_are_lost():
    """The first half saturates: the rest is exact, the lost half's truth is all error (the composite has
    nothing there), e = ‖T_lost‖/‖T‖, as the compositor's score counts a masked pixel."""
    t = _chart()
    lost = np.arange(t.size) < t.size // 2
    s, b = 1000.0 * t, np.where(lost, 1e6, 0.0)
    err, sat = reading_error("E", s, b, np.zeros(t.size), np.zeros(t.size), t, full_well_e=5e4, noise=False)
    want = math.sqrt(np.sum(t[lost] ** 2) / np.sum(t ** 2))
    assert sat == pytest.approx(0.5) and 0.3 < want < 0.9 and err == pytest.approx(want, rel=1e-9)


@pytest.mark.parametrize("camera, width, shape", [
    ((160, 120), None, (120, 160)),     # the camera's own pixel grid by default
    ((160, 90), None, (90, 160)),
    ((400, 300), None, (120, 160)),     # … up to 10 px per stripe (16 stripes): wider costs for nothing
    ((160, 90), 96, (54, 96)),          # a cheaper width keeps the pixel aspect (16:9 here)
    ((160, 90), 12, (27, 48)),          # at least 3 px per stripe (16 stripes)
    ((40, 30), 96, (30, 40)),           # never wider than the camera
])
def test_the_renders_follow_the_camera_unless_a_width_is_given(camera, width, shape):
    base = load_scene(None)
    scene = base.replace(camera=base.camera.replace(resolution=camera))
    model = ImageModel(scene, width=width, n_stripes=16)
    assert model.shape == shape
    assert plan_model(scene, n_stripes=16, width=width).shape == shape
    # each pixel collects the scene camera's electrons: exposure × (w / w_camera)²
    want = base.camera.exposure_s * (shape[1] / camera[0]) ** 2
    assert model.scene.camera.exposure_s == pytest.approx(want)
    with pytest.raises(SceneError, match="width must be an integer of at least 8 pixels, got 4"):
        ImageModel(scene, width=4)


def test_planner_with_the_error_measure_on_a_small_scene():
    scene = load_scene(None)
    model = ImageModel(scene, width=16, n_stripes=4)
    assert model.shape == (12, 16)
    plans = plan(model, np.array([0.05, 0.2, 0.4]))
    assert set(plans) == {"flood", "flood_polarized", "stripes", "stripes_polarized"}
    for mp in plans.values():
        assert np.all((mp.curve.objective >= 0) & (mp.curve.objective <= 1))
    assert set(plans["stripes_polarized"].readings) == {"E_b", "S_hat"}
    with pytest.raises(SceneError, match="measure"):
        plan_model(scene, measure="cqm")


def test_the_planner_s_draft_level_is_a_named_fidelity():
    """``draft`` (the planner's level below preview) is one name among the simulator's; a bad name is one
    error naming them."""
    scene = load_scene(None)
    assert plan_model(scene, fidelity="draft", width=16, n_stripes=4).fidelity is PLAN_FIDELITY["draft"]
    assert plan_model(scene, fidelity="preview", width=16, n_stripes=4).fidelity.name == "preview"
    with pytest.raises(SceneError, match="is not preview, standard, reference, draft"):
        plan_model(scene, fidelity="rough", width=16)


def test_at_standard_eq6_divides_by_the_compositors_preview_map():
    """The compositor's p map is its model rendered at ``preview``, fitted to the flood pair
    (planning/medium_p.py). A plan at ``standard`` predicts Ŝ with that map, not with the standard frame's
    own DOP: its noise-free Ŝ error is the error of eq. 6 computed by hand from the standard flood pair and
    the compositor's map, scored by the compositor's score (imaging/metrics.py). With the frame's own DOP
    Ŝ would be S itself, a different number (HG 0.5, where the two levels' B/(S + B) differ)."""
    from polarstripe.imaging.metrics import signal_error
    from polarstripe.planning.medium_p import p_map_with_model
    from polarstripe.planning.predicted_error import mean_angle, polarized_frames
    from polarstripe.sim.render import render_components
    from polarstripe.sim.scene import with_separation
    from polarstripe.sim.sensor import electrons_per_radiance
    from polarstripe.sim.truth import unscattered_object

    scene = load_scene("bench/scenes/tank_hg05.toml")
    model = ImageModel(scene, fidelity="standard", width=48)
    d = 0.17
    got = objective(model.flood(d), IDEAL_SENSOR, modality="flood", reading="S_hat", measure="error")
    sd = with_separation(model.scene, d, aim=True)
    c = render_components(sd, "flood", "standard")
    s, b, p, chi = c.D + c.A, c.B, np.nan_to_num(c.p), c.chi_rad
    e_b, e_w = polarized_frames(s, b, p, chi, mean_angle(b.ravel(), p.ravel(), chi.ravel()))
    truth = unscattered_object(sd)[0]
    est = p_map_with_model((e_b, e_w), truth <= 0, 0.0, math.inf, sd, "preview")
    e = electrons_per_radiance(sd.camera)                     # scored in electrons, as in DN: cos⁴ in
    s_hat = (e_b * (1 + 1 / est.eq6) + e_w * (1 - 1 / est.eq6)) * e
    want = signal_error(s_hat, truth * e, fit_gain=True)
    exact = signal_error(s * e, truth * e, fit_gain=True)    # Ŝ = S: the frame's own DOP as the map
    assert abs(want - exact) > 0.01                           # the map matters here
    assert got.frame_quality == pytest.approx(1 - want, abs=2e-3)


@pytest.mark.parametrize("fidelity", ["draft", "standard"])
def test_a_stripe_scan_divides_by_the_same_flood_map_after_the_flood(fidelity):
    """A plan evaluates the flood, then the stripes at the same separations; the stripes reuse the flood's
    map (planning/image_model.py ``_flood_map``). Their samples are the ones a fresh model gives, which
    renders the flood again: at ``draft`` (its own frame's B, p, χ, from a render of B and p alone) and at
    ``standard`` (the compositor's map at preview)."""
    scene = load_scene(None)
    fresh = ImageModel(scene, fidelity=fidelity, width=16, n_stripes=4).stripes(0.2)
    model = ImageModel(scene, fidelity=fidelity, width=16, n_stripes=4)
    model.flood(0.2)
    reused = model.stripes(0.2)
    assert len(model._flood_maps) == 1
    for a, b in zip(fresh.flood_dop, reused.flood_dop, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(fresh.backscatter, reused.backscatter)
    # another separation is another map
    assert not np.array_equal(model.stripes(0.4).flood_dop[0], reused.flood_dop[0])
