"""A of full frames (interpolated on the pattern-coordinate grid) against A computed exactly at the pixel."""

import numpy as np
import pytest
from polarstripe.sim.geometry import intersect, pinhole_frame, pixel_rays
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import load_scene
from polarstripe.sim.surface_grid import kappa_nodes

CONVERGED = "xi=16,side=12,grid=none"     # the per-pixel rule at high counts (converged to ~1e-5 here)


def _small_scene():
    s = load_scene(None)
    return s.replace(camera=s.camera.replace(resolution=(160, 120)))


def _pixels_near_stripe(scene, k, n, count, rng):
    """Pixels on the chart whose projector column lies within two stripe widths of stripe k's edges."""
    pr = scene.projector
    proj = pinhole_frame(pr.position, pr.look_at, pr.up, pr.fov_deg, pr.resolution)
    cam = pinhole_frame(scene.camera.position, scene.camera.look_at, scene.camera.up, scene.camera.fov_deg,
                        scene.camera.resolution)
    hits = intersect(scene.objects, cam.position, pixel_rays(cam))
    v = hits.point - proj.position
    col = proj.w / 2 + (v @ proj.r / (v @ proj.f)) / proj.s
    c0, c1 = k * proj.w // n, (k + 1) * proj.w // n
    width = c1 - c0
    near = np.isfinite(hits.t) & (col > c0 - 2 * width) & (col < c1 + 2 * width)
    idx = rng.choice(np.nonzero(near)[0], count, replace=False)
    return np.stack([idx // cam.w, idx % cam.w], axis=1)


@pytest.mark.parametrize(("level", "tol"), [("standard", 1e-2), ("preview", 2e-2)])
def test_stripe_frame_a_near_the_stripe_edges_matches_the_converged_pixel_rule(level, tol):
    scene = _small_scene()
    px = _pixels_near_stripe(scene, 14, 30, 16, np.random.default_rng(3))
    frame = render_components(scene, "stripe:14/30", level, need=("A",), orders="single").A[px[:, 0],
                              px[:, 1]]
    exact = render_components(scene, "stripe:14/30", CONVERGED, pixels=px, need=("A",), orders="single").A
    assert exact.min() > 0
    np.testing.assert_allclose(frame, exact, rtol=tol)


def test_flood_frame_a_matches_the_converged_pixel_rule():
    scene = _small_scene()
    rng = np.random.default_rng(4)
    mask = render_components(scene, "flood", "preview", need=("D",), orders="single").object_mask
    idx = rng.choice(np.flatnonzero(mask), 12, replace=False)
    px = np.stack([idx // 160, idx % 160], axis=1)
    frame = render_components(scene, "flood", "standard", need=("A",), orders="single").A[px[:, 0], px[:, 1]]
    exact = render_components(scene, "flood", CONVERGED, pixels=px, need=("A",), orders="single").A
    np.testing.assert_allclose(frame, exact, rtol=1e-2)


def test_kappa_nodes_put_a_node_on_each_stripe_edge_and_stay_in_range():
    nodes = kappa_nodes(100.0, 900.0, 477.0, 512.0, 12)
    assert nodes[0] == 100.0 and nodes[-1] == 900.0
    assert 477.0 in nodes and 512.0 in nodes
    assert np.all(np.diff(nodes) > 0)
    inside = nodes[(nodes > 477.0) & (nodes < 512.0)]
    assert inside.size >= 5                      # the peak inside the stripe is resolved
    assert 477.0 not in kappa_nodes(600.0, 900.0, 477.0, 512.0, 12)   # edges outside the range are left out
