"""The ground truth of `polarstripe compare` and `simulator/truth`: the unscattered object radiance
(sim/truth.py, docs/physics.md §10.8), against a closed form and the no-scattering limit of the full
render."""

import numpy as np
import pytest
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import Box, Camera, Medium, PlaneObject, Projector, Scene, SceneError, load_scene
from polarstripe.sim.truth import unscattered_object, unscattered_radiance


def _ray(i, j, w=16, h=12, fov_deg=40.0):
    """Pixel (i, j) of a pinhole at the origin looking along +z, up +y (right = −x; docs/physics.md §0.2)."""
    s = 2 * np.tan(np.radians(fov_deg) / 2) / w
    d = np.array([0.0, 0.0, 1.0]) + (j + 0.5 - w / 2) * s * np.array([-1.0, 0, 0]) \
        - (i + 0.5 - h / 2) * s * np.array([0, 1.0, 0])
    return d / np.linalg.norm(d)


def _plane_scene(sigma_t=3.0, albedo=0.9):
    return Scene(medium=Medium(sigma_t=sigma_t, albedo=albedo, extent=Box(min=(-1, -1, 0), max=(1, 1, 0.6))),
                 camera=Camera(position=(0, 0, 0), look_at=(0, 0, 1), resolution=(16, 12), fov_deg=40.0),
                 projector=Projector(model="point", position=(0.1, 0.05, 0.0), intensity_w_sr=2.0),
                 objects=(PlaneObject(point=(0, 0, 0.4), normal=(0, 0, -1), albedo=0.6),))


def test_plane_under_a_point_source_is_the_closed_form():
    """T = ρ cos φ / π · I0 e^{−σ_t(|LO| + |CO|)} / (|LO|² + r_s²) on a plane z = 0.4 m, written out per pixel
    from the pinhole geometry (camera and source on the medium's face, so every path is in the medium)."""
    scene = _plane_scene()
    got = unscattered_radiance(scene)
    src, r_s = np.array([0.1, 0.05, 0.0]), 1e-3
    want = np.empty((12, 16))
    for i in range(12):
        for j in range(16):
            v = _ray(i, j)
            o = v * 0.4 / v[2]
            d_lo = np.linalg.norm(o - src)
            cos_phi = 0.4 / d_lo
            want[i, j] = 0.6 * cos_phi / np.pi * 2.0 * np.exp(-3.0 * (d_lo + np.linalg.norm(o))) / (
                d_lo ** 2 + r_s ** 2)
    np.testing.assert_allclose(got, want, rtol=1e-10)


def test_no_scattered_light_the_sigma_s_to_zero_limit_of_the_full_render():
    """With σ_s = 0 (albedo 0) the full render, every order, is T; as σ_s → 0 it tends to T linearly."""
    base = load_scene(None).replace(camera=Camera(resolution=(40, 30)))
    for sigma_t in (2.0, 8.0):
        absorbing = base.replace(medium=base.medium.replace(sigma_t=sigma_t, albedo=0.0))
        comp = render_components(absorbing, "flood", "standard", orders="all")
        truth = unscattered_radiance(absorbing)
        assert truth.max() > 0 and (truth > 0).sum() > 300
        np.testing.assert_allclose(comp.D + comp.A + comp.B, truth, rtol=1e-12, atol=0)
        # a trace of scattering: the scattered part is of the order of σ_s, the truth does not move
        faint = base.replace(medium=base.medium.replace(sigma_t=sigma_t, albedo=1e-5))
        comp = render_components(faint, "flood", "standard", orders="all")
        chart = comp.surface.chart_band >= 0
        rel = np.abs(comp.S - unscattered_radiance(faint))[chart] / truth[chart]
        assert rel.max() < 1e-3
        np.testing.assert_array_equal(unscattered_radiance(faint), truth)


def test_truth_ignores_the_pattern_and_holds_no_scattered_light_at_density():
    """At σ_t = 10 the water's own S = D + A carries far more (forward-scattered) light than T, whose chart
    keeps the albedo's contrast: band 0 alternates 0.6 and 0.06, Michelson 0.818 up to the source's
    fall-off."""
    scene = load_scene(None).replace(camera=Camera(resolution=(80, 60)))
    scene = scene.replace(medium=scene.medium.replace(sigma_t=10.0))
    truth, surf = unscattered_object(scene)
    flood = render_components(scene, "flood", "preview")
    np.testing.assert_array_equal(surf.chart_band, flood.surface.chart_band)
    np.testing.assert_array_equal(truth, flood.D)           # D is the unscattered light under every order
    band0 = surf.chart_band == 0
    hi, lo = truth[band0 & surf.chart_high].mean(), truth[band0 & ~surf.chart_high].mean()
    assert abs((hi - lo) / (hi + lo) - 0.818) < 0.03
    s_hi, s_lo = flood.S[band0 & surf.chart_high].mean(), flood.S[band0 & ~surf.chart_high].mean()
    assert (s_hi - s_lo) / (s_hi + s_lo) < 0.2                # the water's object light is blurred
    assert flood.S[band0].mean() > 10 * truth[band0].mean()
    pix = np.array([[30, 40], [0, 0], [59, 79]])
    np.testing.assert_array_equal(unscattered_radiance(scene, pix), truth[pix[:, 0], pix[:, 1]])


def test_bad_scene_is_one_clear_error():
    with pytest.raises(SceneError, match="scene must be a Scene"):
        unscattered_radiance({"medium": {}})
