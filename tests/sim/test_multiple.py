"""The higher orders' pieces against closed forms and conservation: the similarity split, the grid's
successive orders, the forward-cone halo, the polarization kept per order; hypothesis properties of the whole
model (energy never created, monotone in albedo, vanishing with σ_t)."""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from polarstripe.sim.multiple import Field, make_grid, propagate, solve_orders, solve_polarized, tail_ratio
from polarstripe.sim.polarization import pair_retention
from polarstripe.sim.psf import N_LADDER, halo_table, radial_stencil, spread
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import Medium, Phase, SceneError, load_scene
from polarstripe.sim.similarity import THETA_C, scaled_medium, truncated_value
from scipy.integrate import quad


def _phase(model, g):
    def hg(mu, gg):
        return (1 - gg * gg) / (4 * np.pi * (1 + gg * gg - 2 * gg * mu) ** 1.5)

    if model == "isotropic":
        return lambda mu: 1 / (4 * np.pi)
    if model == "hg":
        return lambda mu: hg(mu, g)
    from polarstripe.sim.phase import tthg_parameters

    gf, gb, a = tthg_parameters(g)
    return lambda mu: a * hg(mu, gf) + (1 - a) * hg(mu, -gb)


# ------------------------------------------------------------------------------------------ similarity

@pytest.mark.parametrize("model,g", [("tthg", 0.8), ("tthg", 0.5), ("hg", 0.5), ("hg", 0.95), ("hg", -0.4),
                                     ("isotropic", 0.0)])
def test_similarity_split_against_quadrature(model, g):
    """f, g̃ and the cone's ⟨θ²⟩ from closed forms agree with adaptive quadrature of the phase function."""
    p = _phase(model, g)
    c = math.cos(THETA_C)
    f = 2 * np.pi * quad(p, c, 1, points=[0.99, 0.999, 0.9999], limit=400)[0]
    first = 2 * np.pi * quad(lambda m: m * p(m), -1, c, limit=400)[0] / (1 - f)
    th2 = 2 * np.pi * quad(lambda t: t * t * p(math.cos(t)) * math.sin(t), 0, THETA_C, limit=400,
                           points=[1e-3, 1e-2, 0.05])[0] / max(f, 1e-300)
    sc = scaled_medium(Medium(sigma_t=4.0, albedo=0.9, phase=Phase(model, g)))
    assert sc.f == pytest.approx(f, abs=1e-9)
    assert sc.g_tilde == pytest.approx(first, abs=1e-7)
    assert 2 * sc.theta2_x == pytest.approx(th2, rel=1e-3, abs=1e-8)
    assert sc.sigma_s == pytest.approx(0.9 * 4.0 * (1 - f))
    assert sc.sigma_t == pytest.approx(4.0 - f * 0.9 * 4.0)
    # σ̃_s P̃ = σ_s P outside the cone, 0 inside; P̃ integrates to 1
    mu = np.array([-1.0, -0.3, 0.5, 0.8, 0.95])
    want = np.where(mu < c, p(mu) * 0.9 * 4.0, 0.0)
    np.testing.assert_allclose(sc.sigma_s * truncated_value(sc.phase, 1 - mu, 1 + mu), want, rtol=1e-9)
    total = 2 * np.pi * quad(lambda m: truncated_value(sc.phase, 1 - m, 1 + m), -1, 1, points=[c],
                             limit=200)[0]
    assert total == pytest.approx(1.0, rel=1e-6)


def test_similarity_rejects_a_bad_cone():
    with pytest.raises(SceneError, match="theta_c"):
        scaled_medium(Medium(), theta_c=0.0)
    with pytest.raises(SceneError, match="theta_c"):
        scaled_medium(Medium(), theta_c=2.0)


# ------------------------------------------------------------------------------------------ the grid

def test_uniform_emission_in_a_thick_box_gives_s_over_sigma():
    """A uniform isotropic emission s in an optically thick box: fluence s/σ_t deep inside (∫K₀ dV = 1/σ),
    s(1 − E₂(σz)/2)/σ at depth z below a wall (the half-space solution)."""
    grid = make_grid((0, 0, 0), (1, 1, 1), 24)
    sigma = 60.0
    field = propagate(grid, sigma, np.ones(grid.n), np.zeros((*grid.n, 3)))
    c = tuple(k // 2 for k in grid.n)
    assert field.phi[c] == pytest.approx(1 / sigma, rel=0.02)
    assert np.abs(field.flux[c]).max() < 1e-3 / sigma                    # no net flux in the middle
    from scipy.special import expn

    z = 0.5 * grid.h[0]
    assert field.phi[0, c[1], c[2]] == pytest.approx((1 - 0.5 * expn(2, sigma * z)) / sigma, rel=0.03)


def test_a_point_emitter_sends_flux_outward_with_inverse_square_falloff():
    grid = make_grid((-1, -1, -1), (1, 1, 1), 31)
    s0 = np.zeros(grid.n)
    c = tuple(k // 2 for k in grid.n)
    vol = float(np.prod(grid.h))
    s0[c] = 1.0 / vol                                  # 1 W in the centre cell, nothing scatters (σ = 0)
    f = propagate(grid, 0.0, s0, np.zeros((*grid.n, 3)))
    for k in (5, 10):
        r = k * grid.h[0]
        assert f.phi[c[0] + k, c[1], c[2]] == pytest.approx(1 / (4 * np.pi * r * r), rel=0.03)
        assert f.flux[c[0] + k, c[1], c[2], 0] == pytest.approx(1 / (4 * np.pi * r * r), rel=0.03)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(sigma_t=st.floats(0.1, 50.0), albedo=st.floats(0.0, 1.0), g=st.floats(-0.6, 0.6),
       cells=st.integers(4, 12), seed=st.integers(0, 1000))
def test_no_order_creates_energy(sigma_t, albedo, g, cells, seed):
    """Each order scatters at most albedo × the power extinguished of the one before, which is at most
    what was emitted: σ_t ∫φ dV ≤ ∫s dV (light that leaves the box is lost), and so each order ≤ the one
    before and the tail ratio ≤ the albedo."""
    grid = make_grid((0, 0, 0), (0.6, 0.5, 0.4), cells)
    rng = np.random.default_rng(seed)
    s0 = rng.random(grid.n)
    vol = float(np.prod(grid.h))
    f = propagate(grid, sigma_t, s0, np.zeros((*grid.n, 3)))
    assert sigma_t * f.phi.sum() * vol <= s0.sum() * vol * (1 + 0.03)
    quasi = Field(s0, np.zeros((*grid.n, 3)))                 # the unscattered light's fluence
    sol = solve_orders(grid, quasi, sigma_t, albedo * sigma_t, g, orders=4)
    # first order: extinguishes at most what the unscattered light scattered, σ_s ∫φ₀
    assert sigma_t * sol.first.phi.sum() <= albedo * sigma_t * quasi.phi.sum() * 1.03 + 1e-12
    assert sol.ratio <= albedo * 1.03 + 1e-12
    assert np.all(sol.total.phi >= sol.first.phi - 1e-12) and np.all(np.isfinite(sol.total.phi))


def test_tail_ratio_approaches_one_only_for_thick_white_media():
    grid = make_grid((0, 0, 0), (0.6, 0.6, 0.38), 10)
    thin = tail_ratio(grid, 1.0, 1.0, 0.0, 6)
    thick = tail_ratio(grid, 100.0, 100.0, 0.0, 6)
    grey = tail_ratio(grid, 100.0, 50.0, 0.0, 6)
    assert thin < 0.5 and 0.9 < thick <= 0.98 and grey < 0.55


def test_solve_orders_rejects_bad_settings():
    grid = make_grid((0, 0, 0), (1, 1, 1), 4)
    q = Field(np.ones(grid.n), np.zeros((*grid.n, 3)))
    with pytest.raises(ValueError, match="orders"):
        solve_orders(grid, q, 1.0, 1.0, 0.0, orders=0)
    with pytest.raises(ValueError, match="kappa"):
        solve_polarized(grid, q, 1.0, 1.0, 0.0, kappa=1.5)


# ------------------------------------------------------------------------------------------ halo, DOP

@pytest.mark.parametrize("model,g", [("tthg", 0.8), ("hg", 0.5), ("isotropic", 0.0)])
def test_halo_is_fermi_eyges(model, g):
    """One scattering at a uniform point of the path with a cone angle of per-axis variance θ²_x moves the
    end by θ²_x ℓ²/3 per axis (small n); the mixture keeps that variance; rms grows with n as
    √(n/(1 − e^−n))."""
    sc = scaled_medium(Medium(phase=Phase(model, g)))
    t = halo_table(model, g, sc.phase.cos_c)
    assert t.rms[0] == pytest.approx(math.sqrt(sc.theta2_x / 3), rel=0.03)
    n = N_LADDER[-2]
    assert t.rms[-2] == pytest.approx(math.sqrt(sc.theta2_x / 3 * n / -math.expm1(-n)), rel=0.05)
    from polarstripe.sim.psf import WIDTHS

    np.testing.assert_allclose(t.weights.sum(1), 1.0, atol=1e-9)
    np.testing.assert_allclose((t.weights * WIDTHS ** 2).sum(1), 1.0, atol=0.02)
    n_, rms = spread(t, 2.0, np.array([0.0, 0.5]))
    assert n_[0] == 0 and rms[0] == 0 and rms[1] > 0
    pts, w = radial_stencil(t.weights[0])
    assert w.sum() == pytest.approx(1.0) and np.allclose(pts.mean(0), 0, atol=1e-9)


def test_polarization_kept_per_wide_scattering():
    """Twice-backscattered light keeps part of the once-backscattered DOP: all of it with no scattering out
    of the plane of incidence (a pure-backscatter phase function), less the wider the phase function."""
    def iso(omm, opm):
        return np.full(np.shape(omm), 1 / (4 * np.pi))

    def planar(omm, opm):          # only (near-)back and 90°-ish scattering: broad but not isotropic
        return np.exp(-((1 - np.asarray(opm)) ** 2) / 0.02)

    k_iso = pair_retention(iso, 0.2)
    assert 0.3 < k_iso < 0.7
    assert pair_retention(iso, 0.0) > k_iso
    assert 0 <= pair_retention(planar, 0.2) <= 1


# ------------------------------------------------------------------------------------------ properties

def _scene(sigma, albedo, model, g, cam_x, res=(24, 18)):
    s = load_scene(None)
    g = abs(g) if model == "tthg" else g
    return s.replace(medium=s.medium.replace(sigma_t=sigma, albedo=albedo, phase=Phase(model, g)),
                     camera=s.camera.replace(position=(cam_x, 0.0, 0.0), look_at=(cam_x, 0.0, 0.38),
                                             resolution=res))


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(sigma=st.floats(0.5, 12.0), a1=st.floats(0.05, 0.95), da=st.floats(0.02, 0.5),
       model=st.sampled_from(["tthg", "hg", "isotropic"]), g=st.floats(-0.9, 0.95),
       cam_x=st.floats(-0.1, 0.1), pattern=st.sampled_from(["flood", "stripe:7/20", "checker:128:0"]))
def test_monotone_in_albedo(sigma, a1, da, model, g, cam_x, pattern):
    """More albedo at the same extinction only adds light (every path's weight is ω^k): A, B and the
    total never fall."""
    a2 = min(a1 + da, 1.0)
    lo = render_components(_scene(sigma, a1, model, g, cam_x), pattern, "preview")
    hi = render_components(_scene(sigma, a2, model, g, cam_x), pattern, "preview")
    for k in ("A", "B"):
        x, y = getattr(lo, k), getattr(hi, k)
        assert np.all(y >= x * (1 - 1e-6) - 1e-12 * max(x.max(), 1e-300)), k


def test_blurs_move_light_and_do_not_make_it():
    """The halo only redistributes: unmasked, a blob far from the frame's edges keeps its total; masked
    (normalised over the object), a uniform object stays uniform."""
    from polarstripe.sim.psf import blur_image

    h, w = 120, 160
    yy, xx = np.mgrid[0:h, 0:w]
    blob = np.exp(-((xx - 80) ** 2 + (yy - 60) ** 2) / 50.0).astype(np.float32)
    mix = np.array([0.1, 0.15, 0.3, 0.35, 0.1])
    for r in (1.0, 4.0, 9.0):
        rms = np.full((h, w), r, np.float32)
        assert blur_image(blob, rms, mix).sum() == pytest.approx(blob.sum(), rel=2e-3)
    mask = (xx - 80) ** 2 + (yy - 60) ** 2 < 40 ** 2
    out = blur_image(np.where(mask, 1.0, 0.0).astype(np.float32), np.full((h, w), 6.0, np.float32), mix, mask)
    np.testing.assert_allclose(out[mask], 1.0, rtol=1e-4)
    assert np.all(out[~mask] == 0)


def test_quasi_direct_light_never_exceeds_the_unattenuated_light():
    """Folding the cone into the direct light gives back part of the extinction, never more: the quasi-
    direct object radiance lies between the direct light (σ_t) and the light with no medium at all."""
    base = _scene(5.0, 1.0, "tthg", 0.8, 0.0, res=(32, 24))
    d = render_components(base, "flood", "preview", need=("D",), orders="single").D
    free = render_components(base.replace(medium=base.medium.replace(sigma_t=0.0)), "flood", "preview",
                             need=("D",)).D
    from polarstripe.sim.backscatter import scaled_source
    from polarstripe.sim.geometry import intersect, pinhole_frame, pixel_rays
    from polarstripe.sim.higher import _direct_pair
    from polarstripe.sim.orders import plan_orders
    from polarstripe.sim.patterns import parse_pattern
    from polarstripe.sim.render import resolve_fidelity
    from polarstripe.sim.surface import surface_info
    from polarstripe.sim.surface_field import View
    from polarstripe.sim.transport import make_source

    c = base.camera
    cam = pinhole_frame(c.position, c.look_at, c.up, c.fov_deg, c.resolution)
    dirs = pixel_rays(cam)
    hits = intersect(base.objects, cam.position, dirs)
    view = View(base, parse_pattern("flood"), resolve_fidelity("preview"), cam, dirs, hits,
                surface_info(base.objects, hits), None)
    src = make_source(base, parse_pattern("flood"))
    _, quasi = _direct_pair(view, src, scaled_source(src, plan_orders(base)), ("A",))
    q = (quasi * view.surf.albedo).reshape(d.shape)
    assert np.all(q >= d * (1 - 1e-12)) and np.all(q <= free * (1 + 1e-12)) and q.sum() > 2 * d.sum()


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(albedo=st.floats(0.2, 1.0), model=st.sampled_from(["tthg", "hg", "isotropic"]),
       g=st.floats(-0.9, 0.95),
       cam_x=st.floats(-0.1, 0.1))
def test_higher_orders_vanish_with_sigma(albedo, model, g, cam_x):
    """all ÷ single − 1 falls at least in proportion to σ_t as σ_t → 0 (and is 0 below the 1 % rule)."""
    excess = []
    for sigma in (0.4, 0.1, 0.005):
        a = render_components(_scene(sigma, albedo, model, g, cam_x), "flood", "preview")
        b = render_components(_scene(sigma, albedo, model, g, cam_x), "flood", "preview", orders="single")
        excess.append(abs(float((a.D + a.A + a.B).sum() / (b.D + b.A + b.B).sum()) - 1))
    assert excess[2] == 0.0
    assert excess[1] <= 0.5 * excess[0] + 1e-3
