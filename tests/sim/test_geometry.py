"""Compiled ray geometry against plain per-ray code written from the definitions."""

import numpy as np
from polarstripe.sim.geometry import box_interval, intersect, pinhole_frame, pixel_rays
from polarstripe.sim.scene import BoxObject, PlaneObject, SphereObject


def _plain_hit(o, d, obj):
    """(t, normal) of one ray against one object, or (inf, None)."""
    if isinstance(obj, SphereObject):
        c = np.array(obj.center)
        b = (o - c) @ d
        disc = b * b - ((o - c) @ (o - c) - obj.radius ** 2)
        if disc <= 0:
            return np.inf, None
        t = -b - np.sqrt(disc)
        return (t, (o + t * d - c) / obj.radius) if t > 1e-12 else (np.inf, None)
    if isinstance(obj, BoxObject):
        lo, hi = np.array(obj.min), np.array(obj.max)
        t_in, t_out, axis = -np.inf, np.inf, 0
        for k in range(3):
            if d[k] == 0:
                if not lo[k] <= o[k] <= hi[k]:
                    return np.inf, None
                continue
            a, b = sorted(((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]))
            if a > t_in:
                t_in, axis = a, k
            t_out = min(t_out, b)
        if t_in > t_out or t_in <= 1e-12:
            return np.inf, None
        n = np.zeros(3)
        n[axis] = -np.sign(d[axis])
        return t_in, n
    n = np.array(obj.normal)
    if d @ n >= 0:
        return np.inf, None
    t = (np.array(obj.point) - o) @ n / (d @ n)
    if t <= 1e-12:
        return np.inf, None
    if obj.size is not None:
        right = np.cross(-n, obj.up)
        right /= np.linalg.norm(right)
        up = np.cross(right, -n)
        rel = o + t * d - np.array(obj.point)
        if abs(rel @ right) > obj.size[0] / 2 or abs(rel @ up) > obj.size[1] / 2:
            return np.inf, None
    return t, n


def test_intersect_matches_plain_per_ray_code_for_planes_spheres_and_boxes():
    objects = (PlaneObject(point=(0, 0, 0.38), normal=(0, 0, -1), size=(0.3, 0.2)),
               PlaneObject(point=(0.1, 0, 0.3), normal=(0.3, 0, -1), size=(0.2, 0.25)),
               SphereObject(center=(0.05, 0.02, 0.25), radius=0.05),
               BoxObject(min=(-0.1, -0.1, 0.2), max=(0.0, 0.0, 0.3)))
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.5
    d[:20, 0] = 0.0                                        # axis-parallel components
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.array([0.01, -0.02, 0.0])
    hits = intersect(objects, o, d)
    for i in range(d.shape[0]):
        found = [(*_plain_hit(o, d[i], obj), k) for k, obj in enumerate(objects)]
        t, n, k = min(found, key=lambda x: x[0])
        if np.isinf(t):
            assert hits.index[i] == -1 and np.isinf(hits.t[i])
            continue
        assert hits.index[i] == k
        assert hits.t[i] == np.float64(t) or abs(hits.t[i] - t) <= 1e-15 * t
        np.testing.assert_allclose(hits.normal[i], n, atol=1e-15)
    assert (hits.index == 2).any() and (hits.index == 3).any() and (hits.index == -1).any()


def test_box_interval_and_pixel_rays_follow_the_definitions():
    cam = pinhole_frame((0, 0, 0), (0.1, 0, 1), (0, 1, 0), 60.0, (8, 6))
    d = pixel_rays(cam)
    i, j = 4, 5
    want = cam.f + ((j + 0.5) - 4) * cam.s * cam.r - ((i + 0.5) - 3) * cam.s * cam.u
    np.testing.assert_allclose(d[i * 8 + j], want / np.linalg.norm(want), rtol=1e-15)
    np.testing.assert_allclose(pixel_rays(cam, np.array([[i, j]]))[0], d[i * 8 + j], rtol=0, atol=0)
    lo, hi = np.array([-0.3, -0.3, 0.0]), np.array([0.3, 0.3, 0.38])
    o = np.array([0.0, 0.0, -0.1])
    t0, t1 = box_interval(o, d, lo, hi)
    for k in range(d.shape[0]):
        xs = np.linspace(0, 2, 4001)
        pts = o + xs[:, None] * d[k]
        inside = xs[np.all((pts >= lo) & (pts <= hi), axis=1)]
        assert abs(t0[k] - inside[0]) < 1e-3 and abs(t1[k] - inside[-1]) < 1e-3
    par = box_interval(np.array([0.5, 0.0, 0.1]), np.array([[0.0, 0.0, 1.0]]), lo, hi)   # parallel, outside
    assert par[1][0] < par[0][0]
