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
    assert np.all(dn[comp.B > 0] == 4095)                                        # clipped, not wrapped


def test_default_flood_frame_uses_most_of_the_range_without_saturating_the_chart():
    s = load_scene(None)
    c = render_components(s, "flood", "preview")
    m = mean_dn(c.D + c.A + c.B, s.camera)
    assert 0.6 * 4095 < m[c.object_mask].max() < 0.95 * 4095
