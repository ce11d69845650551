"""EMVA 1288 sensor: conversion, noise statistics, clipping, reproducibility."""

import numpy as np
import pytest
from polarstripe.sim.render import render_components, render_frame
from polarstripe.sim.scene import load_scene
from polarstripe.sim.sensor import dark_offset_dn, electrons_per_radiance, expose, mean_dn, noise_std_dn


def test_radiance_to_electrons_on_axis():
    cam = load_scene(None).camera.replace(resolution=(1, 1))
    s = 2 * np.tan(np.radians(cam.fov_deg) / 2) / 1
    photon = 6.62607015e-34 * 299792458.0 / (cam.wavelength_nm * 1e-9)
    want = cam.qe * np.pi * cam.aperture_m ** 2 / 4 * s ** 2 * cam.exposure_s / photon
    assert electrons_per_radiance(cam)[0, 0] == pytest.approx(want, rel=1e-12)


def test_noise_statistics_match_the_model():
    cam = load_scene(None).camera.replace(resolution=(200, 200), fov_deg=1.0)
    k = electrons_per_radiance(cam).mean()
    radiance = np.full((200, 200), 8000.0 / k)
    frames = np.stack([expose(radiance, cam, seed).astype(float) for seed in range(3)])
    assert frames.mean() == pytest.approx(float(mean_dn(radiance, cam).mean()), rel=2e-3)
    want_std = float(noise_std_dn(radiance, cam).mean())
    assert frames.std(axis=(1, 2)).mean() == pytest.approx(want_std, rel=0.03)
    dark = expose(np.zeros((200, 200)), cam, 1).astype(float)
    assert dark.mean() == pytest.approx(dark_offset_dn(cam), abs=0.1)


def test_seeded_and_saturated_frame():
    s = load_scene(None).replace(camera=load_scene(None).camera.replace(resolution=(40, 30)))
    a, _ = render_frame(s, "flood", None, "preview", seed=7)
    b, _ = render_frame(s, "flood", None, "preview", seed=7)
    assert np.array_equal(a, b) and a.dtype == np.uint16
    hot = s.replace(projector=s.projector.replace(intensity_w_sr=1e6))
    dn, comp = render_frame(hot, "flood", None, "preview", seed=1)
    assert dn.max() == 4095 and dn.dtype == np.uint16 and np.all(dn <= 4095)
    # with a lower gain the full well (50 000 e-) fills before the ADC: the lit pixels sit at
    # 50 000 / 20 + 64 = 2564 DN, give or take the read noise (12 e- = 0.6 DN), not at 4095
    low_gain = hot.replace(camera=hot.camera.replace(gain_e_per_dn=20.0))
    dn, comp = render_frame(low_gain, "flood", None, "preview", seed=1)
    assert np.all(np.abs(dn[comp.B > 0].astype(float) - 2564.0) <= 4)


def test_default_flood_frame_uses_most_of_the_range_without_saturating_the_chart():
    s = load_scene(None)
    c = render_components(s, "flood", "preview")
    m = mean_dn(c.D + c.A + c.B, s.camera)
    assert 0.6 * 4095 < m[c.object_mask].max() < 0.95 * 4095


def _ideal(cam, **changes):
    """``cam`` without read noise, dark current, offset and quantisation limits unless given."""
    base = {"read_noise_e": 0.0, "dark_current_e_s": 0.0, "offset_dn": 0.0, "gain_e_per_dn": 1.0,
            "bits": 16, "full_well_e": 1e9}
    return cam.replace(**{**base, **changes})


def test_poisson_shot_noise_variance_equals_the_mean_electrons():
    # gain 1 e-/DN, no read noise, no offset: y = Poisson(mu) exactly, mean mu and variance mu
    cam = _ideal(load_scene(None).camera)
    mu = 200.0
    y = expose(np.ones((300, 400)), cam, 5, electrons=np.full((300, 400), mu)).astype(float)
    assert y.mean() == pytest.approx(mu, rel=3e-3)
    assert y.var() == pytest.approx(mu, rel=0.02)
    assert np.all(y == np.round(y))  # whole electrons: Poisson, not a normal variate


def test_electrons_cap_at_the_full_well_before_the_adc():
    cam = _ideal(load_scene(None).camera, full_well_e=1000.0, gain_e_per_dn=2.0, offset_dn=10.0)
    y = expose(np.ones((20, 30)), cam, 1, electrons=np.full((20, 30), 5000.0))
    assert np.all(y == 1000 / 2 + 10)  # 510 DN exactly, far below the 16-bit ADC's 65535
    low = expose(np.ones((20, 30)), cam.replace(bits=8), 1, electrons=np.full((20, 30), 5000.0))
    assert np.all(low == 255)  # an 8-bit ADC clips first


def test_expose_with_a_precomputed_electrons_map_has_the_emva_mean_and_variance():
    cam = load_scene(None).camera
    lam_e = 500.0
    e_map = np.full((200, 300), lam_e)  # electrons per unit radiance
    for gaussian in (False, True):
        y = expose(np.ones((200, 300)), cam, np.random.default_rng(1), electrons=e_map, gaussian=gaussian)
        dark = cam.dark_current_e_s * cam.exposure_s
        k = cam.gain_e_per_dn
        mean = (lam_e + dark) / k + cam.offset_dn
        var = (cam.read_noise_e ** 2 + lam_e + dark) / k ** 2 + 1 / 12
        assert y.mean() == pytest.approx(mean, rel=0.01)
        assert y.var() == pytest.approx(var, rel=0.05)


def test_the_given_electrons_map_is_the_computed_one():
    """Same seed, same frame, whether the electrons map is passed in or computed inside."""
    cam = load_scene(None).camera.replace(resolution=(24, 18))
    radiance = np.random.default_rng(0).uniform(0.0, 3.0, (18, 24))
    a = expose(radiance, cam, 9)
    b = expose(radiance, cam, 9, electrons=electrons_per_radiance(cam))
    assert np.array_equal(a, b)
