"""The in-situ medium fit (planning/medium_fit.py, docs/planning.md §6) on simulated scans of six media the
planner does not know, and its refusals.

The six-media test takes ~20 s on this machine: each medium needs its frames, a fit (~2 s) and two plans;
it is the fit's acceptance check (docs/planning.md §6) and cannot be split without losing what it shows.
"""

import math

import numpy as np
import pytest
from polarstripe.planning.medium_fit import ScanFrames, downsample, fit_medium
from polarstripe.planning.planner import SceneModel, default_separations, plan
from polarstripe.sim.polarization import least_backscatter_angle
from polarstripe.sim.render import render_components, render_frame
from polarstripe.sim.scene import Phase, load_scene

N = 30
STRIPES = (8, 15, 22)
W, H = 64, 48  # the fit's design size; at 48x36 sigma_t at (3, 0.9) is 8 % uncertain (1 sigma): a coin flip


def _rig():
    sc = load_scene(None)
    return sc.replace(camera=sc.camera.resized((W, H)))


def _medium(scene, sigma_t, g):
    return scene.replace(medium=scene.medium.replace(sigma_t=sigma_t, phase=Phase("tthg", g)))


def _scan(truth, seed=0):
    stripes = {f"stripe:{k}/{N}": [render_frame(truth, f"stripe:{k}/{N}", None, "preview", seed=seed + k)[0]]
               for k in STRIPES}
    flood = [render_frame(truth, "flood", None, "preview", seed=seed + 99)[0]]
    return stripes, flood


def _best(scene, seps):
    model = SceneModel(scene, fidelity="preview", n_stripes=N)
    c = plan(model, seps, modalities=("stripes",))["stripes_polarized"].curve
    return int(np.argmax(c.objective))


MEDIA = [(6.0, 0.7)] + [  # the murkiest, forward-scattering least in the default run (the suite's budget)
    pytest.param(s, g, marks=pytest.mark.long)
    for s, g in ((1.0, 0.9), (1.0, 0.7), (3.0, 0.7), (3.0, 0.9), (6.0, 0.9))]


@pytest.mark.parametrize("sigma_t,g", MEDIA)
def test_six_media_recovered_and_plan_within_one_step(sigma_t, g):
    rig = _rig()  # the planner's prior: the default tank's sigma_t = 5, mean cosine 0.8
    truth = _medium(rig, sigma_t, g)
    stripes, flood = _scan(truth)
    fit = fit_medium(rig, ScanFrames(stripes, flood))
    assert fit.ok, fit.reason
    assert abs(fit.sigma_t_per_m / sigma_t - 1) <= 0.10, (fit.sigma_t_per_m, sigma_t)
    assert abs(fit.mean_cosine - g) <= 0.05, (fit.mean_cosine, g)
    # the uncertainties are finite, positive and cover the error within 4 sigma
    assert 0 < fit.sigma_t_std < 0.15 * fit.sigma_t_per_m and 0 < fit.mean_cosine_std < 0.05
    assert abs(fit.sigma_t_per_m - sigma_t) <= 4 * fit.sigma_t_std + 0.02 * sigma_t
    seps = default_separations(24, 0.02, 0.5)
    est = _medium(rig, fit.sigma_t_per_m, fit.mean_cosine)
    assert abs(_best(est, seps) - _best(truth, seps)) <= 1


def test_p_from_the_analyzer_pair():
    rig = _rig()
    truth = _medium(rig, 3.0, 0.8)
    stripes, flood = _scan(truth, seed=7)
    comp = render_components(truth, "flood", "preview")
    chi = least_backscatter_angle(comp)  # E_b: crossed with the mean backscatter polarization
    eb = render_frame(truth, "flood", chi, "preview", seed=1)[0]
    ew = render_frame(truth, "flood", chi + 90.0, "preview", seed=2)[0]
    free = ~comp.object_mask
    fit = fit_medium(rig, ScanFrames(stripes, flood, polarized_pair=(eb, ew), object_free=free))
    assert fit.ok, fit.reason
    # independent number from the components: the backscatter's own DOP, B-weighted over the region. Through
    # an ideal analyzer (docs/physics.md §4.1) E_w - E_b = B p and E_w + E_b = D + A + B; off the object A
    # (the object's glow, §10.3) is unpolarized and lowers the measured ratio: the fit's model undoes it
    p_true = float(np.sum((comp.B * comp.p)[free]) / np.sum(comp.B[free]))  # the backscatter's DOP
    measured = float(np.median((comp.B * comp.p)[free]) / np.median((comp.D + comp.A + comp.B)[free]))
    assert measured < p_true - 0.05  # what the frames show: the object's light lowers the ratio
    assert abs(fit.p - p_true) < 0.02 and 0 < fit.p_std < 0.05  # 0.5984 against 0.5983 when written


def test_no_visible_sheet_is_refused():
    rig = _rig()
    clear = rig.replace(medium=rig.medium.replace(sigma_t=0.0))  # clear water: no backscatter at all
    stripes, flood = _scan(clear)
    fit = fit_medium(rig, ScanFrames(stripes, flood))
    assert not fit.ok and "no visible sheet" in fit.reason and math.isnan(fit.sigma_t_per_m)


@pytest.mark.parametrize("exposure_scale, why", [
    (300.0, "saturated"),  # the frames at full scale
    (1 / 2000, ""),  # the sheet drowns in read noise: refused (for one reason or another), never a wild value
])
def test_saturated_or_noisy_frames_are_refused(exposure_scale, why):
    rig = _rig()
    truth = _medium(rig, 3.0, 0.8)
    truth = truth.replace(camera=truth.camera.replace(exposure_s=truth.camera.exposure_s * exposure_scale))
    stripes, flood = _scan(truth)
    fit = fit_medium(truth, ScanFrames(stripes, flood))
    assert not fit.ok and fit.reason and why in fit.reason and math.isnan(fit.sigma_t_per_m)


def test_downsample_block_means():
    """The mechanics only: frames rendered at twice the size and fitted at half give sigma_t high (the preview
    model differs between resolutions), docs/planning.md §6."""
    rig = _rig()
    big = rig.replace(camera=rig.camera.replace(resolution=(2 * W, 2 * H)))
    truth = _medium(big, 3.0, 0.7)
    stripes, flood = _scan(truth)
    frames = dict(stripes, flood=flood)
    small, out, n_avg = downsample(big, frames, width=W)
    assert small.camera.resolution == (W, H) and n_avg == 4
    assert np.isclose(out["flood"][0][0, 0], np.mean(np.asarray(flood[0], float)[:2, :2]))
    last = np.asarray(stripes["stripe:8/30"][0], float)[-2:, -2:]
    assert np.isclose(out["stripe:8/30"][0][-1, -1], np.mean(last))
