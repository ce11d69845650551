"""A scan's frames rendered together (sim/scan_render.py) are the frames rendered one by one, to the bit:
stripes, several sheets, a checker and the flood at each level, polarized and circular light, a projector
black level, requested pixels, ports; and the grid's batched solve (sim/multiple.py) is each field's own
solve, to the bit."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.planning.image_model import PLAN_FIDELITY
from polarstripe.sim import geometry_cache
from polarstripe.sim.multiple import Field, GridSolve, make_grid, solve_each, solve_orders, solve_polarized
from polarstripe.sim.render import render_components
from polarstripe.sim.scan_render import render_scan, step_together
from polarstripe.sim.scene import load_scene
from polarstripe.sim.scene_port import Port

FIELDS = ("D", "A", "B", "Bq", "Bu", "Bv", "Sq", "Su")


def _scene(w=64, sigma_t=5.0):
    s = load_scene(None)
    return s.replace(camera=s.camera.resized((w, w * 3 // 4)), medium=s.medium.replace(sigma_t=sigma_t))


def _same_frames(scene, patterns, fidelity, **kw):
    """render_scan against render_components one by one (the cache cleared in between, so neither reads
    what the other made); every field equal to the bit, and not all zero."""
    geometry_cache.clear()
    alone = [render_components(scene, p, fidelity, **kw) for p in patterns]
    geometry_cache.clear()
    together = render_scan(scene, patterns, fidelity, **kw)
    assert len(together) == len(alone)
    for a, b in zip(alone, together, strict=True):
        assert str(a.pattern) == str(b.pattern)
        for k in FIELDS:
            np.testing.assert_array_equal(getattr(b, k), getattr(a, k), err_msg=f"{a.pattern} {k}")
        assert a.B.max() > 0 and (a.D + a.A).max() > 0
    return together


@pytest.mark.parametrize("fidelity", ["preview", "standard", PLAN_FIDELITY["draft"]])
def test_a_scan_together_is_the_frames_one_by_one(fidelity):
    comps = _same_frames(_scene(), ["stripe:3/8", "stripe:4/8", "stripe:1/8:x2", "checker:16:0", "flood"],
                         fidelity)
    assert comps[0].orders.modelled
    assert np.abs(comps[0].Bq).max() > 0            # the polarized chain went through the batch too


def test_circular_light_black_level_and_requested_pixels():
    s = _scene(48)
    pol = s.projector.polarization.replace(quarter_wave_deg=45.0)
    circular = s.replace(projector=s.projector.replace(polarization=pol, black_level=0.05))
    comps = _same_frames(circular, ["stripe:2/6", "stripe:3/6"], "preview")
    assert np.abs(comps[0].Bv).max() > 0
    _same_frames(s, ["stripe:2/6", "flood"], "standard", pixels=np.array([[18, 10], [18, 24], [5, 40]]))


def test_a_scan_through_ports():
    port = Port(distance_m=0.02, thickness_m=0.01, n_glass=1.5, n_water=1.333)
    s = _scene(48, sigma_t=3.0)
    s = s.replace(camera=s.camera.replace(port=port), projector=s.projector.replace(port=port))
    _same_frames(s, ["stripe:2/6", "stripe:3/6"], "preview")


def _fields(grid, count, seed):
    rng = np.random.default_rng(seed)
    phi = rng.random((count, *grid.n))
    flux = rng.normal(size=(count, *grid.n, 3)) * phi[..., None] * 0.3   # |F| past φ/3 in places: cut
    return phi, flux


def test_the_batched_solve_is_each_fields_own_solve():
    grid = make_grid((-0.2, -0.15, 0.0), (0.2, 0.15, 0.45), 10)
    phi, flux = _fields(grid, 5, 1)
    phi[2], flux[2] = 0.0, 0.0                        # a frame with no light in the medium
    both = solve_orders(grid, Field(phi, flux), 4.0, 2.5, 0.3, orders=3)
    pol = solve_polarized(grid, Field(phi, flux), 4.5, 2.5, 0.3, kappa=0.6, orders=3)
    for k in range(5):
        one = solve_orders(grid, Field(phi[k], flux[k]), 4.0, 2.5, 0.3, orders=3)
        for a, b in ((one.first, both.first), (one.total, both.total)):
            np.testing.assert_array_equal(b.phi[k], a.phi)
            np.testing.assert_array_equal(b.flux[k], a.flux)
        own = solve_polarized(grid, Field(phi[k], flux[k]), 4.5, 2.5, 0.3, kappa=0.6, orders=3)
        np.testing.assert_array_equal(pol.phi[k], own.phi)
        np.testing.assert_array_equal(pol.flux[k], own.flux)
    assert both.total.phi[0].max() > both.first.phi[0].max() > 0 and not both.total.phi[2].any()
    requests = [GridSolve(grid, Field(phi[k], flux[k]), 4.0, 2.5, 0.3, 3) for k in range(5)]
    for k, got in enumerate(solve_each(requests)):
        one = solve_orders(grid, Field(phi[k], flux[k]), 4.0, 2.5, 0.3, orders=3)
        np.testing.assert_array_equal(got.total.phi, one.total.phi)
        assert got.count == one.count                  # 0 for the dark frame, as its own solve says


def test_stepping_together_batches_the_requests_of_a_step():
    """Three frames of two steps each are answered in two batches, in the frames' order."""
    grid = make_grid((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), 4)
    phi, flux = _fields(grid, 3, 2)
    seen = []

    def frame(k):
        first = yield GridSolve(grid, Field(phi[k], flux[k]), 3.0, 1.0, 0.2, 2)
        second = yield GridSolve(grid, first.total, 3.0, 1.0, 0.2, 2, kappa=0.5)
        seen.append(k)
        return k, second

    import polarstripe.sim.scan_render as scan

    batches = []
    real = scan.solve_each
    scan.solve_each = lambda reqs, *tol: batches.append(len(reqs)) or real(reqs, *tol)
    try:
        out = step_together([frame(k) for k in range(3)])
    finally:
        scan.solve_each = real
    assert batches == [3, 3] and [k for k, _ in out] == [0, 1, 2]
    own = solve_polarized(grid, solve_orders(grid, Field(phi[1], flux[1]), 3.0, 1.0, 0.2, orders=2).total,
                          3.0, 1.0, 0.2, kappa=0.5, orders=2)
    np.testing.assert_array_equal(out[1][1].phi, own.phi)


def test_the_patches_light_kept_per_scene_is_the_frames_own():
    """The glow's patches lit through the terms a scan keeps (grid_patches.py patch_light) get the numbers
    quasi_irradiance gives with footprint_lit, to the bit, with a sphere shadowing some of them."""
    from polarstripe.sim.grid_patches import (
        footprint_lit,
        object_patches,
        patch_irradiance,
        patch_light,
        quasi_irradiance,
    )
    from polarstripe.sim.patterns import parse_pattern
    from polarstripe.sim.scene import SphereObject
    from polarstripe.sim.transport import make_source

    s = load_scene(None)
    s = s.replace(objects=s.objects + (SphereObject(center=(0.02, 0.0, 0.3), radius=0.04, albedo=0.5),))
    flood = make_source(s, parse_pattern("flood"))
    grid = make_grid(flood.box_lo, flood.box_hi, 16)
    pa = object_patches(s.objects, grid.lo, grid.hi, float(grid.h.min()))
    light = patch_light(flood, s.objects, pa.point, pa.normal, pa.du, pa.dv)
    assert (light.rects[0] & ~light.seen).any()                  # some patches in the frustum are shadowed
    for p in ("flood", "stripe:14/30", "stripe:1/6:x2", "checker:16:0", "gray:1:col:0"):
        src = make_source(s, parse_pattern(p))
        lit = footprint_lit(src, pa.point, pa.du, pa.dv)
        want = quasi_irradiance(src, s.objects, pa.point, pa.normal, lit)
        assert want.max() > 0
        np.testing.assert_array_equal(patch_irradiance(src, light), want, err_msg=p)


def test_what_the_projector_does_not_change_is_kept_for_every_pose():
    """A second separation reuses the first's camera-only values (geometry_cache.camera_only: the camera's
    rays, the view table, the glow's basis, ...) and renders, at every level, the frames of a cold cache."""
    from polarstripe.sim.geometry_cache import camera_only
    from polarstripe.sim.scene import with_separation

    base = _scene(64)
    pats = ["stripe:2/6", "flood"]
    for fidelity in ("preview", "standard", PLAN_FIDELITY["draft"]):
        far = with_separation(base, 0.25)
        assert camera_only(far) == camera_only(with_separation(base, 0.08)) and far != base
        geometry_cache.clear()
        misses = geometry_cache.stats()["misses"]
        cold_scan = render_scan(far, pats, fidelity)
        made_cold = geometry_cache.stats()["misses"] - misses
        geometry_cache.clear()
        render_scan(with_separation(base, 0.08), pats, fidelity)
        misses = geometry_cache.stats()["misses"]
        warm = render_scan(far, pats, fidelity)
        assert geometry_cache.stats()["misses"] - misses < made_cold - 3     # the camera's values were kept
        geometry_cache.clear()
        cold = [render_components(far, p, fidelity) for p in pats]
        for a, b, c in zip(cold, warm, cold_scan, strict=True):
            for k in FIELDS:
                np.testing.assert_array_equal(getattr(b, k), getattr(a, k), err_msg=f"{a.pattern} {k}")
                np.testing.assert_array_equal(getattr(c, k), getattr(a, k), err_msg=f"{a.pattern} {k}")
