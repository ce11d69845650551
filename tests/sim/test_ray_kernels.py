"""The compiled ray geometry called directly: pinhole rays, slab test, object hits, pattern coordinates,
against the pinhole and hit definitions (docs/scene-format.md, docs/physics.md) written out plainly
(conftest) and hand-computed hits."""

import math

import numpy as np
import pytest
from polarstripe.sim.geometry import pack_objects, pinhole_frame
from polarstripe.sim.ray_kernels import (
    HitArrays,
    box_interval_kernel,
    intersect_kernel,
    pixel_rays_kernel,
    projector_coords_kernel,
)
from polarstripe.sim.scene import BoxObject, PlaneObject, SphereObject

POSE = ((0.1, -0.05, 0.0), (0.0, 0.0, 0.4), (0.0, 1.0, 0.0), 55.0)


def test_pixel_rays_follow_the_pinhole_definition(ref):
    w, h = 7, 5
    fr = pinhole_frame(*POSE[:3], POSE[3], (w, h))
    rows = np.repeat(np.arange(h, dtype=float), w)
    cols = np.tile(np.arange(w, dtype=float), h)
    out = np.empty((w * h, 3))
    pixel_rays_kernel(fr.kernel_args(), rows, cols, out)
    cam = ref.frame(*POSE[:3], POSE[3], w, h)
    want = np.array([ref.ray(cam, i, j) for i in range(h) for j in range(w)])
    np.testing.assert_allclose(out, want, rtol=0, atol=1e-15)


def test_box_interval_is_the_slab_test(ref):
    rng = np.random.default_rng(3)
    lo, hi = np.array([-0.3, -0.2, 0.0]), np.array([0.3, 0.2, 0.5])
    origin = rng.uniform(-0.5, 0.7, (40, 3))
    dirs = rng.normal(size=(40, 3))
    dirs[:5, 0] = 0.0                                # axis-parallel rays
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t0, t1 = np.empty(40), np.empty(40)
    box_interval_kernel(origin, dirs, lo, hi, t0, t1)
    for k in range(40):
        a, b = ref.slab(origin[k], dirs[k], lo, hi)
        if b >= a:
            assert (t0[k], t1[k]) == pytest.approx((a, b), abs=1e-14)
        else:
            assert t1[k] < t0[k]


def test_nearest_hits_of_a_plane_a_sphere_and_a_box():
    """From the origin: a sphere (centre (0, 0, 1), r 0.2) in front of a plane along +z (t = 0.8), a box
    [0.4, 0.6]×[−.1, .1]×[0.9, 1.1] entered through z = 0.9, a 0.2 m square about (0, 0.5, 2), a miss."""
    objs = (PlaneObject(point=(0.0, 0.5, 2.0), normal=(0.0, 0.0, -1.0)),
            SphereObject(center=(0.0, 0.0, 1.0), radius=0.2),
            BoxObject(min=(0.4, -0.1, 0.9), max=(0.6, 0.1, 1.1)))
    kinds, params = pack_objects(objs)
    d_box = np.array([0.5, 0.0, 0.9]) / math.hypot(0.5, 0.9)
    d_plane = np.array([0.0, 0.55, 2.0]) / math.hypot(0.55, 2.0)     # misses the sphere
    dirs = np.array([[0.0, 0.0, 1.0], d_box, d_plane, [0.0, 1.0, 0.0]])
    out = HitArrays(np.empty(4), np.empty(4, np.int64), np.empty((4, 3)), np.empty((4, 3)))
    intersect_kernel(kinds, params, np.zeros((1, 3)), dirs, out)
    assert out.index.tolist() == [1, 2, 0, -1]
    assert out.t[0] == pytest.approx(0.8, rel=1e-14)
    np.testing.assert_allclose(out.normal[0], [0, 0, -1], atol=1e-14)
    assert out.t[1] == pytest.approx(0.9 / d_box[2], rel=1e-14)        # enters through the face z = 0.9
    np.testing.assert_allclose(out.normal[1], [0, 0, -1])
    assert out.t[2] == pytest.approx(math.hypot(0.55, 2.0), rel=1e-14)
    np.testing.assert_allclose(out.point[2], [0.0, 0.55, 2.0], atol=1e-14)
    assert out.t[3] == math.inf and out.point[3].tolist() == [0, 0, 0] and out.normal[3].tolist() == [0, 0, 0]


def test_projector_coordinates_invert_the_pinhole_rays(ref):
    w, h = 64, 48
    fr = pinhole_frame(*POSE[:3], POSE[3], (w, h))
    proj = ref.frame(*POSE[:3], POSE[3], w, h)
    p = np.array(POSE[0])
    pts = np.array([p + 0.7 * ref.ray(proj, 10, 20), p + 0.3 * ref.ray(proj, 0, 63), [0.1, -0.05, -1.0]])
    col, row, depth = (np.empty(3) for _ in range(3))
    projector_coords_kernel(fr.kernel_args(), pts, col, row, depth)
    for k in range(2):
        assert (col[k], row[k]) == pytest.approx(ref.projector_pixel(proj, pts[k]), abs=1e-10)
    assert (col[0], row[0]) == pytest.approx((20.5, 10.5), abs=1e-10)   # pixel centres
    assert depth[2] < 0 and (col[2], row[2]) == (-1.0, -1.0)           # behind the projector
