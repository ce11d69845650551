"""Mueller DOP (paper eq. 15) against docs/physics.md §5, and the analyzer (Malus)."""

import numpy as np
import pytest
from polarstripe.sim.polarization import analyzer, dop_backscatter, least_backscatter_angle
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import load_scene

DEG = np.radians


@pytest.mark.parametrize("theta, unpol, perp, par, diag", [
    (90, 0.667, 0.800, 0.000, 0.667), (120, 0.429, 0.800, 0.500, 0.714), (135, 0.250, 0.800, 0.667, 0.750),
    (150, 0.111, 0.800, 0.750, 0.778), (165, 0.028, 0.800, 0.789, 0.794), (180, 0.0, 0.800, 0.800, 0.800)])
def test_dop_table_delta_0_2(theta, unpol, perp, par, diag):
    t = DEG(theta)
    assert dop_backscatter(t, 0.0) == pytest.approx(unpol, abs=1e-3)
    assert dop_backscatter(t, 1.0, DEG(90)) == pytest.approx(perp, abs=1e-3)
    assert dop_backscatter(t, 1.0, 0.0) == pytest.approx(par, abs=1e-3)
    assert dop_backscatter(t, 1.0, DEG(45)) == pytest.approx(diag, abs=1e-3)


@pytest.mark.parametrize("delta, p", [(0.1, 0.9), (0.3, 0.7)])
def test_backscatter_dop_is_one_minus_delta(delta, p):
    assert dop_backscatter(np.pi, 1.0, 0.3, delta) == pytest.approx(p, abs=1e-12)


def test_rendered_p_near_0_8_and_malus_extrema():
    s = load_scene(None)
    c = render_components(s, "flood", "preview", pixels=np.array([(20, 20), (240, 600), (450, 100)]),
                          orders="single")
    assert np.all((c.p > 0.7) & (c.p <= 0.8 + 1e-9))
    angles = np.arange(0, 180, 0.25)
    k1, k2 = 1.0, 1.0 / s.camera.polarizer.extinction_ratio
    vals = np.array([analyzer(c, a) for a in angles])
    tot = c.D + c.A + c.B
    np.testing.assert_allclose(vals.max(0), 0.5 * (k1 + k2) * tot + 0.5 * (k1 - k2) * c.B * c.p, rtol=1e-4)
    np.testing.assert_allclose(vals.min(0), 0.5 * (k1 + k2) * tot - 0.5 * (k1 - k2) * c.B * c.p, rtol=1e-4)
    np.testing.assert_allclose(analyzer(c, None), tot)
    best = least_backscatter_angle(c)
    assert analyzer(c, best).sum() < analyzer(c, best + 90).sum()
    # source polarized along its own up axis; backscatter stays ≈ vertical, so the crossed analyzer is ≈ 0°
    assert min(best, 180 - best) < 15


def test_constant_dop_model():
    s = load_scene(None)
    s = s.replace(medium=s.medium.replace(dop=s.medium.dop.replace(model="constant", p=0.55)))
    c = render_components(s, "flood", "preview", pixels=np.array([(20, 20), (240, 600)]), orders="single")
    np.testing.assert_allclose(c.p, 0.55, rtol=1e-12)
