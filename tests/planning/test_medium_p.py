"""p from an analyzer pair with the medium's model (planning/medium_p.py, docs/physics.md §4.2), against the
backscatter's own DOP from the components (B-weighted over the region), with the analyzer off the mean
backscatter angle by 15° (a calibration that missed): the model's fit takes the angle, the frames alone
read the DOP lowered by the object's light and the angle."""

import numpy as np
import pytest
from polarstripe.imaging.polarization import recover_signal
from polarstripe.planning.medium_p import p_map_with_model, p_of_pair, p_with_model
from polarstripe.sim.polarization import analyzer, least_backscatter_angle, polarizer_transmittances
from polarstripe.sim.render import render_components, render_frame
from polarstripe.sim.scene import Phase, load_scene, with_separation
from polarstripe.sim.sensor import dark_offset_dn, full_scale_dn
from polarstripe.sim.truth import unscattered_object


@pytest.mark.parametrize("sigma_t,g", [(1.0, 0.7), (8.0, 0.9)])
def test_the_model_reads_the_backscatter_dop_through_object_light_and_a_missed_angle(sigma_t, g):
    s = load_scene(None)
    s = s.replace(camera=s.camera.resized((64, 48)),
                  medium=s.medium.replace(sigma_t=sigma_t, phase=Phase("tthg", g)))
    sd = with_separation(s, 0.25)
    c = render_components(sd, "flood", "preview")
    free = unscattered_object(sd)[0] <= 1e-9
    truth = float(np.sum((c.B * c.p)[free]) / np.sum(c.B[free]))
    chi = least_backscatter_angle(c) + 15.0
    pair = (render_frame(sd, "flood", chi, "preview", seed=1)[0],
            render_frame(sd, "flood", chi + 90.0, "preview", seed=2)[0])
    args = (pair, free, dark_offset_dn(sd.camera), full_scale_dn(sd.camera) - 0.5)
    p, std, why = p_with_model(*args, sd, "preview")
    assert not why and abs(p - truth) < 0.01 and 0 < std < 0.01
    alone, _, _ = p_of_pair(*args)
    assert alone < truth - 0.05


def test_the_models_map_is_the_dop_the_pair_sees_and_eq6_with_it_gives_s():
    """Noise-free pair through an analyzer 15° off the mean angle: the map is the pair's own DOP per pixel,
    (k1 − k2)/(k1 + k2)·p·cos 2(χ − ψ) (ψ the co-polarized angle), and eq. 6 with it gives (k1 + k2)·S exactly
    (E_b + E_w = (k1 + k2)(S + B), E_w − E_b = (k1 − k2)·B·p·cos 2(χ − ψ)); one p̂ does not."""
    s = load_scene(None)
    sd = with_separation(s.replace(camera=s.camera.resized((64, 48))), 0.2)
    c = render_components(sd, "flood", "preview")
    free = unscattered_object(sd)[0] <= 1e-9
    psi = least_backscatter_angle(c) + 90.0 + 15.0  # co-polarized, off by 15°
    pair = (analyzer(c, psi + 90.0), analyzer(c, psi))
    est = p_map_with_model(pair, free, 0.0, np.inf, sd, "preview", components=c)
    k1, k2 = polarizer_transmittances(sd.camera.polarizer.extinction_ratio)
    seen = (k1 - k2) / (k1 + k2) * c.p * np.cos(2.0 * (c.chi_rad - np.radians(psi)))
    assert est.source == "model" and not est.note
    np.testing.assert_allclose(est.eq6, np.clip(seen, 0.05, 1.0), atol=2e-3)
    truth = float(np.sum((c.B * c.p)[free]) / np.sum(c.B[free]))
    assert est.p == pytest.approx(truth * (k1 - k2) / (k1 + k2), abs=2e-3)
    np.testing.assert_allclose(recover_signal(*pair, est.eq6), (k1 + k2) * c.S, atol=2e-3 * np.max(c.S))
    one = recover_signal(*pair, est.p)  # one p: the backscatter under- and over-subtracted across the image
    assert np.max(np.abs(one - (k1 + k2) * c.S)) > 0.02 * np.max(c.S)


def test_without_backscatter_in_the_model_the_map_comes_from_the_frames():
    s = load_scene(None)
    sd = s.replace(camera=s.camera.resized((40, 30)))
    pair = (np.full((30, 40), 300.0), np.full((30, 40), 500.0))  # DOP 0.25 everywhere
    c = render_components(sd, "flood", "preview")
    c.B[:] = 0.0
    est = p_map_with_model(pair, None, 0.0, np.inf, sd, "preview", components=c)
    assert est.source == "frames" and "model's p map not used" in est.note
    np.testing.assert_allclose(est.eq6, 0.25, atol=1e-9)


def test_a_pair_crossed_per_pixel_is_fitted_without_the_angle():
    """A polarization camera's ``local`` rule crosses each pixel to its own angle: E_w − E_b = κ·p·B, no
    cos 2(χ − ψ). The map is then κ·p per pixel and the medium's p the B-weighted DOP; fitted with the angle,
    the pair would read high (the model's cos < 1 away from the mean angle, the pair's not)."""
    s = load_scene(None)
    sd = with_separation(s.replace(camera=s.camera.resized((64, 48))), 0.2)
    c = render_components(sd, "flood", "preview")
    free = unscattered_object(sd)[0] <= 1e-9
    e_b, e_w = 0.5 * (c.S + c.B * (1 - c.p)), 0.5 * (c.S + c.B * (1 + c.p))  # eqs. 4-5 at each pixel's χ
    est = p_map_with_model((e_b, e_w), free, 0.0, np.inf, sd, "preview", components=c, crossed=True)
    truth = float(np.sum((c.B * c.p)[free]) / np.sum(c.B[free]))
    np.testing.assert_allclose(est.eq6, np.clip(c.p, 0.05, 1.0), atol=1e-6)
    assert est.p == pytest.approx(truth, abs=1e-6)
    angled = p_map_with_model((e_b, e_w), free, 0.0, np.inf, sd, "preview", components=c)
    assert angled.p > truth
