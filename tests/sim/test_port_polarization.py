"""The port's diattenuation (sim/port.py ``diattenuate``, docs/physics.md §11): the Fresnel transmittances of
s and p light against the textbook's closed forms (normal incidence, Brewster's angle, the pile of plates),
and the frames through a camera port and a projector port against Fresnel and Malus computed here,
independently of the model's kernels."""

from __future__ import annotations

import math

import numpy as np
import pytest
from polarstripe.sim.geometry import intersect, pinhole_frame, pixel_rays
from polarstripe.sim.port import diattenuate, light_to, port_geometry, transmittances_sp
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import load_scene
from polarstripe.sim.scene_port import Port
from polarstripe.sim.transport import make_source

N_G, N_W = 1.5, 1.333


def _fresnel(theta, n1, n2):
    """(T_s, T_p, θ_t) of one interface from the textbook's amplitude coefficients (Hecht §4.6)."""
    ci = math.cos(theta)
    st = n1 * math.sin(theta) / n2
    ct = math.sqrt(1.0 - st * st)
    ts, tp = 2 * n1 * ci / (n1 * ci + n2 * ct), 2 * n1 * ci / (n2 * ci + n1 * ct)
    scale = n2 * ct / (n1 * ci)                  # power transmittance = (n₂ cos θ_t / n₁ cos θ_i)·t²
    return scale * ts * ts, scale * tp * tp, math.asin(st)


def _slab(theta, n_a=1.0, n_g=N_G, n_w=N_W):
    """(T_s, T_p) through air → glass → water at air angle θ."""
    s1, p1, tg = _fresnel(theta, n_a, n_g)
    s2, p2, _ = _fresnel(tg, n_g, n_w)
    return s1 * s2, p1 * p2


def test_normal_incidence_changes_no_polarization():
    """At normal incidence T_s = T_p = (1 − R₁)(1 − R₂): the port scales every Stokes component by T and
    leaves the DOP and the angle as they were."""
    ts, tp = transmittances_sp(0.0, 0.01, 1.0, N_G, N_W, True)
    t = (1 - ((1 - N_G) / (1 + N_G)) ** 2) * (1 - ((N_G - N_W) / (N_G + N_W)) ** 2)
    assert ts == pytest.approx(t, rel=1e-12) and tp == pytest.approx(t, rel=1e-12)
    out = diattenuate(ts, tp, 0.3, math.sqrt(1 - 0.09), 1.0, 0.5, -0.4, 0.2)
    np.testing.assert_allclose(out, [t, 0.5 * t, -0.4 * t, 0.2 * t], rtol=1e-12)


@pytest.mark.parametrize("deg", [10.0, 25.0, 40.0, 55.0])
def test_transmittances_are_the_textbook_fresnel(deg):
    q = math.sin(math.radians(deg))                       # Snell's invariant in air
    assert transmittances_sp(q, 0.01, 1.0, N_G, N_W, True) == pytest.approx(_slab(math.radians(deg)),
                                                                             rel=1e-12)
    assert transmittances_sp(q, 0.01, 1.0, N_G, N_W, False) == (1.0, 1.0)     # coated


def test_brewster_angle_one_face():
    """Unpolarized light through one air–glass face at Brewster's angle tan θ_B = n: T_p = 1, T_s =
    4n²/(n² + 1)², so it leaves with DOP (n² − 1)²/((n² + 1)² + 4n²) = 0.0799 for n = 1.5, along p."""
    n = N_G
    q = math.sin(math.atan(n))
    ts, tp = transmittances_sp(q, 0.0, 1.0, n, n, True)          # t = 0: a single face into index n
    assert tp == pytest.approx(1.0, abs=1e-12)
    assert ts == pytest.approx(4 * n * n / (n * n + 1) ** 2, rel=1e-12)
    i, qq, uu, v = diattenuate(ts, tp, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    assert qq / i == pytest.approx((n * n - 1) ** 2 / ((n * n + 1) ** 2 + 4 * n * n), rel=1e-12)
    assert qq / i == pytest.approx(0.0799, abs=1e-4) and uu == 0.0 and v == 0.0


def test_brewster_angle_pile_of_one_plate():
    """A glass plate in air at Brewster's angle (both faces at Brewster): T_p = 1, T_s = (2n/(n² + 1))⁴, the
    pile-of-plates DOP (1 − T_s)/(1 + T_s) = 0.159 for one plate of n = 1.5; p light passes whole."""
    n = N_G
    ts, tp = transmittances_sp(math.sin(math.atan(n)), 0.01, 1.0, n, 1.0, True)
    ts_plate = (2 * n / (n * n + 1)) ** 4
    assert tp == pytest.approx(1.0, abs=1e-12) and ts == pytest.approx(ts_plate, rel=1e-12)
    i, qq, _, _ = diattenuate(ts, tp, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    assert qq / i == pytest.approx((1 - ts_plate) / (1 + ts_plate), rel=1e-12) and qq / i > 0.15
    # light polarized along p keeps its power, along s loses 1 − T_s; at 45° it turns toward p
    assert diattenuate(ts, tp, 1.0, 0.0, 1.0, 1.0, 0.0, 0.0)[0] == pytest.approx(1.0)
    assert diattenuate(ts, tp, 1.0, 0.0, 1.0, -1.0, 0.0, 0.0)[0] == pytest.approx(ts_plate)
    i, qq, uu, _ = diattenuate(ts, tp, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0)
    assert math.hypot(qq, uu) / i == pytest.approx(1.0)                     # still fully polarized
    assert 0.5 * math.atan2(uu, qq) == pytest.approx(math.atan(math.sqrt(ts_plate)), rel=1e-12)   # Jones


def _wall_scene(cport=None, pport=None, dop=1.0):
    s = load_scene(None)
    return s.replace(camera=s.camera.resized((40, 30)).replace(port=cport),
                     projector=s.projector.replace(port=pport, polarization=s.projector.polarization.replace(
                         dop=dop)),
                     medium=s.medium.replace(sigma_t=0.0))


PORT = Port(distance_m=0.02, thickness_m=0.01, n_glass=N_G, n_water=N_W)


def test_camera_port_polarizes_the_object_light_radially():
    """Behind a glass port the object's unpolarized light comes out with DOP (T_p − T_s)/(T_p + T_s) of the
    pixel's air angle, its angle radial in the image (the p axis), and D is T = ½(T_s + T_p) of the coated
    port's (textbook Fresnel of the pixel's ray)."""
    px = np.array([[15, 20], [15, 2], [2, 20], [3, 3], [27, 35], [10, 28], [6, 12]])
    glass = render_components(_wall_scene(PORT), "flood", "preview", pixels=px, orders="single")
    coated = render_components(_wall_scene(PORT.replace(coated=True)), "flood", "preview", pixels=px,
                               orders="single")
    cam = glass.scene.camera
    fr = pinhole_frame(cam.position, cam.look_at, cam.up, cam.fov_deg, cam.resolution)
    assert glass.object_mask.sum() >= 5
    for k in np.nonzero(glass.object_mask)[0]:
        row, col = px[k]
        x, y = (col + 0.5 - fr.w / 2) * fr.s, (fr.h / 2 - row - 0.5) * fr.s
        theta = math.atan(math.hypot(x, y))
        ts, tp = _slab(theta)
        assert glass.D[k] / coated.D[k] == pytest.approx(0.5 * (ts + tp), rel=1e-6)
        assert math.hypot(glass.Sq[k], glass.Su[k]) / glass.D[k] == pytest.approx((tp - ts) / (tp + ts),
                                                                                  abs=1e-9)
        if theta > 0.05:
            assert glass.Sq[k] / glass.D[k] == pytest.approx((tp - ts) / (tp + ts) * (x * x - y * y)
                                                             / (x * x + y * y), abs=1e-9)
            assert glass.Su[k] / glass.D[k] == pytest.approx((tp - ts) / (tp + ts) * 2 * x * y
                                                             / (x * x + y * y), abs=1e-9)
    assert np.all(coated.Sq == 0) and np.all(coated.Su == 0)


def test_projector_port_passes_a_polarized_source_as_jones_says():
    """A linearly polarized source through a glass port: the surface's irradiance is T_s·e_s² + T_p·e_p² of
    the E-field's s and p parts (Jones), against ½(T_s + T_p) for an unpolarized source."""
    px = np.stack(np.meshgrid(np.arange(1, 30, 4), np.arange(1, 40, 4), indexing="ij"), -1).reshape(-1, 2)
    pol = render_components(_wall_scene(None, PORT, 1.0), "flood", "preview", pixels=px, orders="single",
                            need=("D",))
    unpol = render_components(_wall_scene(None, PORT, 0.0), "flood", "preview", pixels=px, orders="single",
                              need=("D",))
    lit = unpol.D > 0
    assert lit.sum() >= 20
    px, pol_d, unpol_d = px[lit], pol.D[lit], unpol.D[lit]
    s = pol.scene
    pr = s.projector
    c = s.camera
    cam = pinhole_frame(c.position, c.look_at, c.up, c.fov_deg, c.resolution)
    points = intersect(s.objects, np.asarray(cam.position, float), pixel_rays(cam, px)).point
    geo = port_geometry(pr.port, pr.position, np.subtract(pr.look_at, pr.position))
    e = np.asarray(make_source(s, "flood").e_field, float)
    ratios, expected = pol_d / unpol_d, []
    for a in light_to(geo, points).air:
        ts, tp = _slab(math.acos(a @ geo.normal))
        sv = np.cross(a, geo.normal)
        sv /= np.linalg.norm(sv)
        es, ep = e @ sv, e @ np.cross(sv, a)
        expected.append((ts * es * es + tp * ep * ep) / (es * es + ep * ep) / (0.5 * (ts + tp)))
    np.testing.assert_allclose(ratios, expected, rtol=1e-9)
    assert np.ptp(ratios) > 1e-3                                       # the effect is there to be seen
