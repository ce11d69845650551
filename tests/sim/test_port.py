"""Flat refractive ports (sim/port.py, sim/port_render.py, docs/physics.md §11): closed forms (the field of
view in water, the n² of the radiance theorem, Fresnel at normal incidence), the irradiance factor J against
a ray tube traced by an independent Snell's law, the inverse against the forward map, and a port of indices 1
against the pinhole model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from polarstripe.sim import port_render
from polarstripe.sim.geometry import pinhole_frame
from polarstripe.sim.orders import plan_orders
from polarstripe.sim.port import light_to, port_geometry, radiance_factor, water_rays
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import SceneError, load_scene, scene_from_dict, scene_to_dict
from polarstripe.sim.scene_port import GLASS_TANK, Port

N_W, N_G = 1.333, 1.5


def _snell(d, n, n1, n2):
    """An independent vector Snell's law: d unit incident, n unit normal along the travel."""
    c = d @ n
    eta = n1 / n2
    return eta * d + (math.sqrt(1.0 - eta * eta * (1.0 - c * c)) - eta * c) * n


def _trace(p, a, n, d, t):
    """Pinhole p, air direction a, through faces at n·(X − p) = d and d + t: (exit point, water direction)."""
    x1 = p + a * d / (a @ n)
    g = _snell(a, n, 1.0, N_G)
    x2 = x1 + g * t / (g @ n)
    return x2, _snell(g, n, N_G, N_W)


def test_field_of_view_narrows_as_snell_says():
    """The image edge's water ray leaves at sin θ_w = (n_a/n_w)·sin θ_a whatever the glass (a slab's faces
    are parallel): the default 60° fov becomes 2·asin(sin 30°/1.333) = 44.06° in water."""
    cam = pinhole_frame((0, 0, -0.05), (0, 0, 1), (0, 1, 0), 60.0, (64, 48))
    port = Port(distance_m=0.02, thickness_m=0.012, n_glass=N_G, n_water=N_W)
    geo = port_geometry(port, cam.position, cam.f)
    edge = np.array([[cam.h / 2 - 0.5, -0.5], [cam.h / 2 - 0.5, cam.w - 0.5]])   # continuous col 0 and w
    air = np.stack([cam.f + (c + 0.5 - cam.w / 2) * cam.s * cam.r for c in edge[:, 1]])
    air /= np.linalg.norm(air, axis=1, keepdims=True)
    _, water, _, _ = water_rays(geo, air)
    theta_w = np.degrees(np.arccos(water @ cam.f))
    assert theta_w == pytest.approx([math.degrees(math.asin(math.sin(math.radians(30)) / N_W))] * 2, abs=1e-9)
    assert 2 * theta_w[0] == pytest.approx(44.06, abs=0.01)


def test_forward_matches_an_independent_snell_trace_and_the_inverse_undoes_it():
    geo = port_geometry(Port(distance_m=0.03, thickness_m=0.01, n_glass=N_G, n_water=N_W, normal=(0.1, 0, 1)),
                        (0.2, 0.05, -0.06), (0.3, 0.1, 1.0))
    rng = np.random.default_rng(3)
    air = geo.normal + 0.6 * rng.normal(size=(20, 3))
    air /= np.linalg.norm(air, axis=1, keepdims=True)
    origins, water, _, _ = water_rays(geo, air)
    for a, o, w in zip(air, origins, water, strict=True):
        e, v = _trace(geo.apex, a, geo.normal, geo.d, geo.t)
        np.testing.assert_allclose(o, e, atol=1e-14)
        np.testing.assert_allclose(w, v, atol=1e-14)
    back = light_to(geo, origins + 0.25 * water)
    assert back.ok.all()
    np.testing.assert_allclose(back.air, air, atol=1e-12)
    np.testing.assert_allclose(back.exit, origins, atol=1e-12)


def test_irradiance_factor_is_the_traced_ray_tube():
    """J = dΩ_air/dA_⊥: the cross-section of a thin tube of air rays traced by the independent Snell's law,
    at the point, per solid angle."""
    geo = port_geometry(Port(distance_m=0.02, thickness_m=0.015, n_glass=N_G, n_water=N_W), (0, 0, 0),
                        (0, 0, 1))
    eps = 1e-6
    for a in ([0.0, 0.0, 1.0], [0.3, 0.1, 1.0], [0.5, -0.4, 1.0]):
        a = np.array(a) / np.linalg.norm(a)
        e1 = np.cross(a, [1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.cross(a, [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        x, w = _trace(geo.apex, a, geo.normal, geo.d, geo.t)
        y = x + 0.3 * w
        corners = []
        for da in ((0, 0), (eps, 0), (0, eps)):
            aa = a + da[0] * e1 + da[1] * e2
            xx, ww = _trace(geo.apex, aa / np.linalg.norm(aa), geo.normal, geo.d, geo.t)
            corners.append(xx + ww * ((y - xx) @ w) / (ww @ w))
        area = np.linalg.norm(np.cross(corners[1] - corners[0], corners[2] - corners[0]))
        assert light_to(geo, y[None]).J[0] == pytest.approx(eps * eps / area, rel=1e-5)


def test_radiance_theorem_at_normal_incidence():
    """Through a vanishing port the irradiance on the axis is (n_w/n_a)²/z² (the solid angle compressed by
    n²), and the radiance a camera sees of water radiance is (n_a/n_w)² of it (coated); with Fresnel the loss
    at normal incidence is (1 − R₁)(1 − R₂), R = ((n₁ − n₂)/(n₁ + n₂))²."""
    z = 0.4
    thin = port_geometry(Port(distance_m=1e-9, thickness_m=0.0, n_water=N_W, coated=True), (0, 0, 0),
                         (0, 0, 1))
    assert light_to(thin, np.array([[0.0, 0.0, z]])).J[0] * z * z == pytest.approx(N_W ** 2, rel=1e-7)
    assert radiance_factor(thin, np.ones(1))[0] == pytest.approx(1 / N_W ** 2)
    glass = port_geometry(Port(distance_m=0.01, thickness_m=0.01, n_glass=N_G, n_water=N_W), (0, 0, 0),
                          (0, 0, 1))
    _, _, trans, _ = water_rays(glass, np.array([[0.0, 0.0, 1.0]]))
    r1, r2 = ((1 - N_G) / (1 + N_G)) ** 2, ((N_G - N_W) / (N_G + N_W)) ** 2
    assert trans[0] == pytest.approx((1 - r1) * (1 - r2), rel=1e-12)
    assert (N_W / 1.0) ** 2 > 1.7          # the limit is not a trivial one


def _scene(port=None, pport=None, sigma_t=2.0, w=48):
    s = load_scene(None)
    return s.replace(camera=s.camera.resized((w, w * 3 // 4)).replace(port=port),
                     projector=s.projector.replace(port=pport), medium=s.medium.replace(sigma_t=sigma_t))


UNIT = Port(distance_m=0.0, thickness_m=0.0, n_air=1.0, n_glass=1.0, n_water=1.0)


@pytest.mark.parametrize("pattern", ["stripe:12/30", "checker:64:32", "gray:0:row:1:xor3", "gray:1:col:0"])
def test_a_port_of_index_one_is_the_pinhole(pattern):
    """With every index 1 the port's rays are the pinhole's: D, B and B's Stokes agree with the pinhole
    model's own kernels (validated against Mitsuba) to the quadratures' precision; also for an XOR row code
    (its lit state changes at the base's column lines too) and a Gray bit of 2-pixel stripes (~500 lit
    pieces on a ray across the pattern)."""
    pin = render_components(_scene(), pattern, "preview", orders="single", need=("D", "B", "p"))
    port = render_components(_scene(UNIT, UNIT), pattern, "preview", orders="single", need=("D", "B", "p"))
    for k, tol in (("D", 1e-4), ("B", 1e-3), ("Bq", 1e-3)):
        a, b = getattr(pin, k), getattr(port, k)
        assert np.abs(a - b).max() <= tol * np.abs(a).max(), k


@pytest.mark.parametrize("pattern, tol", [("checker:64:32", 0.01), ("flood", 0.01), ("stripe:12/30", 0.10)])
def test_surface_term_through_a_port_of_index_one(pattern, tol):
    """A at pixels on the chart: the port's hemisphere rule against the pinhole model's (its beam rule for
    a stripe, whose lit wedge the hemisphere's azimuths resolve to ~7 % of the peak at ``standard``)."""
    px = np.array([[18, c] for c in range(14, 34, 2)])
    pin = render_components(_scene(), pattern, "standard", orders="single", pixels=px, need=("A",)).A
    port = render_components(_scene(UNIT, UNIT), pattern, "standard", orders="single", pixels=px,
                             need=("A",)).A
    assert pin.max() > 0 and np.abs(port - pin).max() <= tol * pin.max()


def test_glass_port_darkens_and_narrows():
    """Through water behind glass the camera sees less (T·(n_a/n_w)² ≈ 0.54) of a narrower view: the chart
    fills more of the image."""
    pin = render_components(_scene(sigma_t=0.0), "flood", "preview", orders="single", need=("D",))
    port = Port(distance_m=0.02, thickness_m=0.01, n_glass=N_G, n_water=N_W)
    through = render_components(_scene(port, port, sigma_t=0.0), "flood", "preview", orders="single",
                                need=("D",))
    assert through.object_mask.sum() > 1.5 * pin.object_mask.sum()
    h, w = pin.D.shape
    centre = (slice(h // 2 - 2, h // 2 + 2), slice(w // 2 - 2, w // 2 + 2))
    assert 0.3 < through.D[centre].mean() / pin.D[centre].mean() < 0.9


def test_no_port_never_enters_the_port_model(monkeypatch):
    """The default scene (no port) renders with the pinhole model only: its frames are those of before."""
    def refuse(*_a, **_k):
        raise AssertionError("port model entered")

    monkeypatch.setattr("polarstripe.sim.render.port_parts", refuse)
    render_components(_scene(), "stripe:3/30", "preview")
    with pytest.raises(AssertionError, match="port model"):
        render_components(_scene(UNIT), "stripe:3/30", "preview")
    assert not port_render.has_port(load_scene(None))


def test_ports_plan_all_orders_as_a_pinhole_does():
    """Through ports the higher orders are modelled (sim/port_higher.py) with the pinhole's error bound."""
    plan = plan_orders(_scene(GLASS_TANK, GLASS_TANK, sigma_t=5.0))
    assert plan.modelled and plan.expected_error == 0.10 and plan.single_error > 0.5


def test_scene_keys_preset_and_round_trip():
    s = scene_from_dict({"camera": {"port": {"distance_m": 0.02, "thickness_m": 0.005, "n_glass": 1.49}}})
    assert s.camera.port == Port(distance_m=0.02, thickness_m=0.005, n_glass=1.49)
    assert s.projector.port is None
    assert scene_from_dict(scene_to_dict(s)) == s
    tank = scene_from_dict({"preset": "glass_tank", "camera": {"resolution": [64, 48]}})
    assert tank.camera.port == GLASS_TANK and tank.projector.port == GLASS_TANK
    assert tank.camera.position[2] == pytest.approx(-0.03) and tank.camera.resolution == (64, 48)
    assert scene_from_dict(scene_to_dict(tank)) == tank
    assert load_scene(None).camera.port is None


@pytest.mark.parametrize("data, match", [
    ({"camera": {"port": {"distance": 0.1}}}, "unknown key camera.port.distance"),
    ({"camera": {"port": "aquarium"}}, "camera.port must be a table or one of glass_tank"),
    ({"camera": {"port": {"n_water": 0.5}}}, "camera.port.n_water must be a refractive index"),
    ({"camera": {"port": {"normal": [1, 0, 0]}}}, "does not look through the port"),
    ({"preset": "lab"}, "preset must be one of glass_tank"),
])
def test_bad_port_keys_are_one_clear_error(data, match):
    with pytest.raises(SceneError, match=match):
        scene_from_dict(data)
