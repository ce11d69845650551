"""Several light sheets per frame (``stripe:I/N:xK``, msgs/patterns.py) in the model: light adds up, so a
frame of K sheets must be the sum of K one-sheet frames rendered on their own. The one-sheet renders take
the one-sheet code paths (one pyramid, one column interval, one grid source); the K-sheet render the union
paths (K pyramids' intervals concatenated, lit fractions summed), so the sum is an independent check."""

import numpy as np
import pytest
from polarstripe.sim.geometry import pinhole_frame
from polarstripe.sim.grid_sources import source_field
from polarstripe.sim.multiple import make_grid
from polarstripe.sim.patterns import lit_intervals, parse_pattern, pattern_lit, single_sheets
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import load_scene
from polarstripe.sim.transport import make_source

MULTI = "stripe:1/9:x3"          # sheets 1, 4, 7 of 9
SINGLES = ("stripe:1/9", "stripe:4/9", "stripe:7/9")


@pytest.fixture(scope="module")
def scene():
    s = load_scene(None)
    return s.replace(camera=s.camera.replace(resolution=(64, 48)))


def test_the_sheets_of_a_pattern_are_the_one_sheet_stripes_at_its_positions():
    assert [str(p) for p in single_sheets(parse_pattern(MULTI))] == list(SINGLES)


def test_the_all_orders_grid_source_of_three_sheets_is_the_sum_of_the_sheets(scene):
    src = make_source(scene, parse_pattern(MULTI))
    grid = make_grid(src.box_lo, src.box_hi, 10)
    multi = source_field(grid, src, scene.objects)
    parts = [source_field(grid, make_source(scene, parse_pattern(t)), scene.objects) for t in SINGLES]
    phi, flux = sum(p.phi for p in parts), sum(p.flux for p in parts)
    assert phi.max() > 0 and all(p.phi.sum() > 0.05 * phi.sum() for p in parts)    # every sheet lights some
    np.testing.assert_allclose(multi.phi, phi, rtol=1e-10, atol=1e-12 * phi.max())
    np.testing.assert_allclose(multi.flux, flux, rtol=1e-10, atol=1e-12 * np.abs(flux).max())


def test_the_lit_set_and_the_lit_intervals_are_the_union_of_the_sheets(scene):
    pr = scene.projector
    frame = pinhole_frame(pr.position, pr.look_at, pr.up, pr.fov_deg, pr.resolution)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-0.3, 0.3, 4000), rng.uniform(-0.2, 0.2, 4000),
                           rng.uniform(0.05, 0.38, 4000)])
    lit = pattern_lit(parse_pattern(MULTI), frame, pts)
    each = [pattern_lit(parse_pattern(t), frame, pts) for t in SINGLES]
    assert lit.sum() > 0 and np.array_equal(lit, np.logical_or.reduce(each))
    assert sum(e.astype(int) for e in each).max() == 1                # the sheets are disjoint
    dirs = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    x0, x1 = np.zeros(len(pts)), np.full(len(pts), 0.6)
    ray, lo, hi = lit_intervals(parse_pattern(MULTI), frame, np.zeros(3), dirs, x0, x1)
    length = np.bincount(ray, hi - lo, minlength=len(pts))
    total = sum(np.bincount(r, h - low, minlength=len(pts))
                for r, low, h in (lit_intervals(parse_pattern(t), frame, np.zeros(3), dirs, x0, x1)
                                  for t in SINGLES))
    assert length.max() > 0
    np.testing.assert_allclose(length, total, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("orders", ["all", "single"])
def test_a_three_sheet_frame_is_the_sum_of_three_one_sheet_frames(scene, orders):
    """D, A (all orders; single scattering's A sums its sheets by construction, so it is left out there)
    and B to rounding; the backscatter's Stokes of orders >= 2 only to 5 % of its largest value: the
    fitted law gives them the orientation of single wide-angle scattering at the pixel (sim/backscatter.py
    add_polarized_orders), which for K sheets is that of their sum, not a sum of K orientations."""
    need = ("D", "A", "B", "p") if orders == "all" else ("D", "B", "p")
    multi = render_components(scene, MULTI, "preview", need=need, orders=orders)
    parts = [render_components(scene, t, "preview", need=need, orders=orders) for t in SINGLES]
    for name in ("D", "B") + (("A",) if orders == "all" else ()):
        total = sum(getattr(p, name) for p in parts)
        assert total.max() > 0
        np.testing.assert_allclose(getattr(multi, name), total, rtol=0, atol=1e-6 * total.max(), err_msg=name)
    for name in ("Bq", "Bu"):
        total = sum(getattr(p, name) for p in parts)
        tol = (0.05 if orders == "all" else 1e-9) * np.abs(total).max()
        np.testing.assert_allclose(getattr(multi, name), total, rtol=0, atol=tol, err_msg=name)
