"""The public entry point: fidelity parsing, the constant-DOP Stokes, requested pixels, the black level and
the camera-grid A of non-planar objects."""

import math

import numpy as np
import pytest
from polarstripe.sim.render import FIDELITY, Fidelity, render_components, resolve_fidelity
from polarstripe.sim.scene import DopModel, SceneError, SphereObject, load_scene
from scipy.ndimage import binary_erosion


def _small(**camera):
    s = load_scene(None)
    return s.replace(camera=s.camera.replace(resolution=(64, 48), **camera))


def test_fidelity_levels_and_explicit_counts():
    assert resolve_fidelity("preview") is FIDELITY["preview"]
    fid = resolve_fidelity("xi=9,theta=3,phi=7,side=2,grid=8x5")
    assert (fid.xi_nodes, fid.hemi_theta, fid.hemi_phi, fid.a_side, fid.a_grid) == (9, 3, 7, 2, (8, 5))
    assert resolve_fidelity("xi=9,grid=none").a_grid is None
    assert resolve_fidelity("xi=9").hemi_phi == FIDELITY["standard"].hemi_phi
    own = Fidelity("mine", 5, 2, 3, None)
    assert resolve_fidelity(own) is own
    for bad in ("fast", "xi=0", "xi=4,grid=1x9", "nodes=4", "side=-1"):
        with pytest.raises(SceneError, match="fidelity"):
            resolve_fidelity(bad)


def test_constant_dop_model_gives_p_and_the_source_polarization_angle():
    """DOP model ``constant``: p = p_medium·DOP_L everywhere B > 0, χ the source's E-field angle in the
    camera frame. The projector's up is world y and its E-field is at 90° from its right, so χ = 90°."""
    s = _small()
    s = s.replace(medium=s.medium.replace(dop=DopModel(model="constant", p=0.7)),
                  projector=s.projector.replace(polarization=s.projector.polarization.replace(dop=0.9)))
    c = render_components(s, "flood", "preview", need=("B", "p"), orders="single")
    lit = c.B > 0
    assert lit.mean() > 0.9
    np.testing.assert_allclose(c.p[lit], 0.63, rtol=1e-12)
    np.testing.assert_allclose(np.abs(c.chi_rad[lit]), math.pi / 2, rtol=1e-12)


def test_requested_pixels_are_those_of_the_full_frame():
    s = _small()
    px = np.array([(0, 0), (24, 32), (47, 63), (10, 50)])
    full = render_components(s, "stripe:14/30", "standard", orders="single")
    part = render_components(s, "stripe:14/30", "standard", pixels=px, orders="single")
    for name in ("D", "B", "Bq", "Bu"):
        np.testing.assert_array_equal(getattr(part, name), getattr(full, name)[px[:, 0], px[:, 1]])


def test_black_level_adds_that_fraction_of_the_flood():
    """A projector whose black is b of its white: (1 − b)·pattern + b·flood, for every component."""
    s = _small()
    b = 0.05
    dimmed = s.replace(projector=s.projector.replace(black_level=b))
    dim = render_components(dimmed, "stripe:14/30", "preview", orders="single")
    on, flood = (render_components(s, p, "preview", orders="single") for p in ("stripe:14/30", "flood"))
    for name in ("D", "A", "B", "Bq", "Bu"):
        np.testing.assert_allclose(getattr(dim, name), (1 - b) * getattr(on, name) + b * getattr(flood, name),
                                   rtol=1e-12, atol=1e-15)


def test_camera_grid_a_of_a_sphere_is_near_the_exact_per_pixel_value():
    """Non-planar objects get A on a camera grid, interpolated: against A computed at every pixel. Near the
    silhouette a pixel may lean on one far node (errors of tens of %), so the bound is on the bulk."""
    s = _small().replace(objects=(SphereObject(center=(0.0, 0.0, 0.25), radius=0.08, albedo=0.5),))
    grid = render_components(s, "flood", "standard", need=("A",), orders="single")
    hit = np.argwhere(grid.object_mask)
    exact = render_components(s, "flood", "standard", pixels=hit, need=("A",), orders="single").A
    assert exact.min() > 0
    err = np.abs(grid.A[hit[:, 0], hit[:, 1]] / exact - 1)
    assert np.median(err) < 0.01
    inner = binary_erosion(grid.object_mask, iterations=3)[hit[:, 0], hit[:, 1]]
    assert np.percentile(err[inner], 90) < 0.025


@pytest.mark.parametrize("pixels", [np.array([[0, 64]]), np.array([[-1, 0]]), np.array([[0.5, 1.0]]),
                                    np.array([1, 2])])
def test_bad_pixels_and_patterns_are_scene_errors(pixels):
    s = _small()
    with pytest.raises(SceneError, match="pixels"):
        render_components(s, "flood", "preview", pixels=pixels, orders="single")
    point = s.replace(projector=s.projector.replace(model="point"))
    with pytest.raises(SceneError, match="pinhole"):
        render_components(point, "stripe:1/30", "preview", orders="single")
