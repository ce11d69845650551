"""The pattern averaged over the glow's patches and the source's beams (docs/physics.md §10.3).

A checker finer than the grid's patches must light each patch by half (its area average), not by the value at
the patch's centre: point samples alias the checker, and a checker and its complement then give different
object light. Independent numbers: a brute-force average of the checker over a rectangle, the flood render
and linearity (a checker plus its complement is the flood)."""

import dataclasses

import numpy as np
import pytest
from polarstripe.sim.grid_patches import footprint_lit, glow_field, object_patches, quasi_irradiance
from polarstripe.sim.grid_sources import lit_fraction
from polarstripe.sim.multiple import make_grid
from polarstripe.sim.patterns import parse_pattern
from polarstripe.sim.render import FIDELITY, render_components
from polarstripe.sim.scene import load_scene, with_separation
from polarstripe.sim.transport import make_source


@pytest.fixture(scope="module")
def scene():
    base = with_separation(load_scene(None), 0.187)          # the simulator demo's pose
    return base.replace(camera=base.camera.replace(resolution=(160, 120)))


def _checker_brute(size, shift, c0, c1, r0, r1, n=1200):
    col = c0 + (np.arange(n) + 0.5) / n * (c1 - c0)
    row = r0 + (np.arange(n) + 0.5) / n * (r1 - r0)
    lit = (np.floor((col[:, None] - shift) / size) + np.floor(row[None, :] / size)) % 2 == 0
    return lit.mean()


def test_checker_lit_fraction_is_the_area_average(scene):
    rng = np.random.default_rng(3)
    for size, shift in ((16, 0), (16, 16), (7, 3), (64, 100)):
        src = make_source(scene, parse_pattern(f"checker:{size}:{shift}"))
        c0, r0 = rng.uniform(0, 400, 6), rng.uniform(0, 300, 6)
        c1, r1 = c0 + rng.uniform(0.5, 90, 6), r0 + rng.uniform(0.5, 90, 6)
        got = lit_fraction(src, c0, c1, r0, r1)
        want = [_checker_brute(size, shift % (2 * size), *b) for b in zip(c0, c1, r0, r1, strict=True)]
        np.testing.assert_allclose(got, want, atol=3e-3)


def _preview_patches(scene):
    st = FIDELITY["preview"].higher
    src = make_source(scene, parse_pattern("flood"))
    grid = make_grid(src.box_lo, src.box_hi, st.cells)
    return grid, object_patches(scene.objects, grid.lo, grid.hi, st.patch_cells * float(grid.h.min()))


def test_fine_checker_lights_every_patch_by_half(scene):
    grid, pa = _preview_patches(scene)
    flood_src = make_source(scene, parse_pattern("flood"))
    inside = footprint_lit(flood_src, pa.point, pa.du, pa.dv)
    assert inside.sum() >= 4                                 # the wall's patches the projector reaches
    fr = {p: footprint_lit(make_source(scene, parse_pattern(p)), pa.point, pa.du, pa.dv)
          for p in ("checker:16:0", "checker:16:16")}
    np.testing.assert_allclose(fr["checker:16:0"] + fr["checker:16:16"], inside, atol=1e-12)
    np.testing.assert_allclose(fr["checker:16:0"][inside > 0], 0.5, atol=0.01)
    stripes = sum(footprint_lit(make_source(scene, parse_pattern(f"stripe:{k}/30")), pa.point, pa.du, pa.dv)
                  for k in range(30))
    np.testing.assert_allclose(stripes, inside, atol=1e-9)   # stripes add up to the flood


def test_a_patch_smaller_than_a_pixel_takes_its_centres_value(scene):
    _, pa = _preview_patches(scene)
    src = make_source(scene, parse_pattern("checker:16:0"))
    tiny = footprint_lit(src, pa.point, pa.du * 1e-9, pa.dv * 1e-9)
    point = quasi_irradiance(src, [], pa.point, pa.normal) > 0
    np.testing.assert_array_equal(tiny > 0.5, point)


def test_glow_of_checker_and_complement_is_half_the_floods(scene):
    grid, pa = _preview_patches(scene)
    phi = {}
    for p in ("checker:16:0", "checker:16:16", "flood"):
        src = make_source(scene, parse_pattern(p))
        lit = footprint_lit(src, pa.point, pa.du, pa.dv)
        e = quasi_irradiance(src, scene.objects, pa.point, pa.normal, lit)
        phi[p] = glow_field(grid, pa, 0.6 * e, src.sigma_t, scene.objects, 16).phi
    a, b, f = phi["checker:16:0"], phi["checker:16:16"], phi["flood"]
    np.testing.assert_allclose(a + b, f, rtol=1e-9, atol=1e-12 * f.max())
    big = f > 0.05 * f.max()
    np.testing.assert_allclose(a[big] / f[big], 0.5, atol=0.01)
    np.testing.assert_allclose(b[big] / f[big], 0.5, atol=0.01)


def test_object_light_of_checker_and_complement_agree_at_preview(scene):
    """The whole model at `preview` (patches 1.5 grid cells, ~9 cm, against 7 mm squares on the wall): the
    object light A of a checker and of its complement each carry half the flood's, on average over the
    object (point-sampled patches gave 0.491 and 0.509)."""
    a = {p: render_components(scene, p, "preview", need=("A",)) for p in
         ("checker:16:0", "checker:16:16", "flood")}
    obj = a["flood"].surface.object_id >= 0
    m = {p: float(c.A[obj].mean()) for p, c in a.items()}
    np.testing.assert_allclose(a["checker:16:0"].A + a["checker:16:16"].A, a["flood"].A, rtol=1e-6,
                               atol=1e-9 * m["flood"])
    assert abs(m["checker:16:0"] / m["flood"] - 0.5) < 0.003
    assert abs(m["checker:16:0"] - m["checker:16:16"]) / m["flood"] < 0.004


def test_the_patch_spacing_no_longer_changes_the_split(scene):
    """The symptom it guards against: the split between checker and complement went 1.3e-2, 1.7e-3, 4.5e-3
    for patch spacings 1.5, 1, 0.5 cells; area-averaged it is the same at every spacing."""
    out = []
    for pc in (1.5, 1.0, 0.5):
        fid = dataclasses.replace(FIDELITY["preview"],
                                  higher=dataclasses.replace(FIDELITY["preview"].higher, patch_cells=pc))
        c = [render_components(scene, p, fid, need=("A",)) for p in ("checker:16:0", "checker:16:16")]
        obj = c[0].surface.object_id >= 0
        out.append(float(np.abs(c[0].A - c[1].A)[obj].mean()))
    assert max(out) < 1.25 * min(out), out
