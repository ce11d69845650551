"""The geometry cache across a scan's frames (sim/geometry_cache.py): a cached render is bit-identical to the
uncached path, a changed scene recomputes, and nothing a caller gets can change what the next frame reads."""

import numpy as np
import pytest
from polarstripe.sim import geometry_cache
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import Camera, SphereObject, load_scene, with_separation

PARTS = ("D", "A", "B", "Bq", "Bu")


def _same(a, b):
    for k in PARTS:
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    np.testing.assert_array_equal(a.surface.object_id, b.surface.object_id)


def _scan(scene, patterns, fidelity):
    """Uncached, then twice through the cache (the second from what the first left), per pattern."""
    geometry_cache.clear()
    for pat in patterns:
        with geometry_cache.disabled():
            plain = render_components(scene, pat, fidelity)
        first = render_components(scene, pat, fidelity)
        again = render_components(scene, pat, fidelity)
        _same(plain, first)
        _same(plain, again)


def test_preview_half_resolution_frames_are_bit_identical():
    """640×480 at preview: the half-resolution path (full rays, half rays, coarse B rays all cached)."""
    scene = load_scene(None)
    before = geometry_cache.stats()["hits"]
    _scan(scene, ("stripe:14/30", "flood", "stripe:3/30", "checker:16:0"), "preview")
    assert geometry_cache.stats()["hits"] > before + 20      # the cache was used, not bypassed


@pytest.mark.parametrize("fidelity", ["standard", "preview"])
def test_shadowed_sphere_black_level_and_point_source_are_bit_identical(fidelity):
    base = load_scene(None).replace(camera=Camera(resolution=(96, 72)))
    sphere = base.replace(objects=base.objects + (SphereObject(center=(0.02, 0.0, 0.3), radius=0.04,
                                                              albedo=0.5),))
    _scan(sphere, ("stripe:12/30", "checker:10:0", "flood"), fidelity)
    black = sphere.replace(projector=sphere.projector.replace(black_level=0.05))
    _scan(black, ("stripe:12/30",), fidelity)
    point = base.replace(projector=base.projector.replace(model="point"))
    _scan(point, ("flood",), fidelity)


def test_a_moved_source_recomputes_and_cached_arrays_are_read_only():
    scene = load_scene(None).replace(camera=Camera(resolution=(64, 48)))
    geometry_cache.clear()
    near = render_components(scene, "stripe:14/30", "standard")
    moved = with_separation(scene, 0.35)
    far = render_components(moved, "stripe:14/30", "standard")
    with geometry_cache.disabled():
        far_plain = render_components(moved, "stripe:14/30", "standard")
    _same(far, far_plain)
    assert not np.array_equal(near.D, far.D)
    with pytest.raises(ValueError):
        near.surface.object_id[0, 0] = 5              # the cache's own array: read-only
    # requested pixels bypass the cache and agree with the frame at those pixels (A by its own rule)
    px = np.array([[24, 32], [10, 5], [40, 60]])
    some = render_components(moved, "stripe:14/30", "standard", pixels=px)
    np.testing.assert_array_equal(some.D, far.D[px[:, 0], px[:, 1]])
