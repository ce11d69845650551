"""The compiled kernels called directly, against closed forms and brute-force quadrature."""

import math

import numpy as np
import pytest
from polarstripe.sim import kernels
from polarstripe.sim.kernel_records import (
    Intervals,
    Light,
    Medium,
    PhaseArgs,
    Polarization,
    Quadrature,
    Rays,
    Stokes,
    SurfacePoints,
)
from scipy.integrate import quad

BOX_LO, BOX_HI = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0])


def _quadrature(nodes, width=math.pi, splits=()):
    t, w = np.polynomial.legendre.leggauss(nodes)
    gl_t, gl_w = np.zeros((3, nodes)), np.zeros((3, nodes))
    for k in range(3):
        gl_t[k], gl_w[k] = t, w
    subs = np.zeros((3, 5), np.int64)
    subs[:, :5] = np.linspace(0, nodes - 1, 5).round().astype(np.int64)
    return Quadrature(nodes, gl_t, gl_w, np.full(3, nodes, np.int64), subs, np.full(3, 5, np.int64),
                      float(width), np.array(splits, float))


def _line(light, medium, phase, origin, d, x0, x1, nodes=64, width=math.pi, splits=()):
    out = Stokes(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
    kernels.line_integrals(light, medium, phase, _quadrature(nodes, width, splits),
                           Polarization(False, False, False, np.array([0.0, 1.0, 0.0]), 1.0, 0.0),
                           Rays(np.asarray(origin, float).reshape(1, 3), np.asarray(d, float).reshape(1, 3),
                                np.zeros(1)),
                           Intervals(np.zeros(1, np.int64), np.array([x0]), np.array([x1])), out)
    return out.b[0]


def _hg(mu, g):
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * mu) ** 1.5)


@pytest.mark.parametrize("mu", [-1.0, -0.3, 0.0, 0.7, 1.0])
def test_phase_value_is_hg_and_two_term_hg(mu):
    omm, opm = 1.0 - mu, 1.0 + mu
    assert kernels.phase_value(PhaseArgs(0, 0.0, 0.0, 0.0), omm, opm) == pytest.approx(1 / (4 * np.pi))
    hg = kernels.phase_value(PhaseArgs(1, 0.8, 0.0, 0.0), omm, opm)
    assert hg == pytest.approx(_hg(mu, 0.8), rel=1e-12)
    want = 0.9 * _hg(mu, 0.9) + 0.1 * _hg(mu, -0.5)
    assert kernels.phase_value(PhaseArgs(2, 0.9, 0.5, 0.9), omm, opm) == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize("a, b, want", [
    ((0.0, 0.0, 0.0), (0.5, 0.0, 0.0), 0.5),            # inside
    ((-3.0, 0.0, 0.0), (3.0, 0.0, 0.0), 2.0),           # through
    ((0.0, 0.0, 0.0), (0.0, 0.0, 4.0), 1.0),            # leaves through one face
    ((2.0, 2.0, 0.0), (2.0, -2.0, 0.0), 0.0),           # parallel to a face, outside
    ((-2.0, -2.0, -2.0), (2.0, 2.0, 2.0), 2 * math.sqrt(3)),   # the diagonal
])
def test_segment_in_box(a, b, want):
    assert kernels.segment_in_box(*a, *b, BOX_LO, BOX_HI) == pytest.approx(want, rel=1e-14, abs=1e-15)


def test_isotropic_clear_medium_line_integral_is_the_arctan_closed_form():
    """σ_t = 0, isotropic: B = σ_s I0/(4π h_e)·[atan(u1/h_e) − atan(u0/h_e)] with h_e² = h² + r_s²."""
    h, rs, ss, i0 = 0.1, 0.02, 0.7, 3.0
    light = Light(np.array([[h, 0.0, 0.3]]), rs, i0, True, np.zeros((0, 3)))
    b = _line(light, Medium(0.0, ss, BOX_LO, BOX_HI), PhaseArgs(0, 0.0, 0.0, 0.0), (0, 0, 0), (0, 0, 1), 0.0,
              0.9, nodes=32)
    he = math.hypot(h, rs)
    want = ss * i0 / (4 * math.pi * he) * (math.atan(0.6 / he) - math.atan(-0.3 / he))
    assert b == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize("inside", [True, False])
def test_hg_line_integral_matches_adaptive_quadrature(inside):
    """eq. 13 along a ray, HG g = 0.8, σ_t = 3: the kernel vs scipy quad in x (source inside the box, and
    outside where only the light path's part in the box attenuates)."""
    st, ss, g = 3.0, 2.4, 0.8
    src = np.array([0.15, 0.05, 0.1]) if inside else np.array([0.15, 0.05, -1.5])
    d = np.array([0.1, 0.0, 1.0])
    d /= np.linalg.norm(d)
    light = Light(src.reshape(1, 3), 0.0, 1.0, inside, np.zeros((0, 3)))
    b = _line(light, Medium(st, ss, BOX_LO, BOX_HI), PhaseArgs(1, g, 0.0, 0.0), (0, 0, 0), d, 0.0, 0.9,
              width=1 - g, splits=[f * (1 - g) for f in (0.3, 1.0, 3.0)])

    def f(x):
        y = x * d
        v = y - src
        dly = np.linalg.norm(v)
        light_path = dly if inside else kernels.segment_in_box(*src, *y, BOX_LO, BOX_HI)
        return ss * _hg(-(v @ d) / dly, g) * np.exp(-st * (light_path + x)) / dly ** 2

    want = quad(f, 0.0, 0.9, limit=400, epsabs=0, epsrel=1e-12)[0]
    assert b == pytest.approx(want, rel=1e-9)


def test_facing_factor_is_the_lambertian_cosine_at_the_source_point():
    """With ``facing`` the integrand gains max(0, n·(Y − L))/d_LY (the caller clips the interval to the
    side the surface faces, as surface_term does; behind it the factor is 0)."""
    st, ss = 1.0, 1.0
    src = np.array([0.2, 0.0, 0.5])
    n = np.array([[0.0, 0.0, -1.0]])                    # facing −z: only the points with z < 0.5 count
    light = Light(src.reshape(1, 3), 0.0, 1.0, True, n)
    args = Medium(st, ss, BOX_LO, BOX_HI), PhaseArgs(0, 0.0, 0.0, 0.0), (0, 0, 0), (0, 0, 1)
    b = _line(light, *args, 0.0, 0.5)

    def f(x):
        v = np.array([0.0, 0.0, x]) - src
        dly = np.linalg.norm(v)
        return ss / (4 * np.pi) * np.exp(-st * (dly + x)) / dly ** 2 * (-v[2] / dly)

    want = quad(f, 0.0, 0.5, limit=200, epsabs=0, epsrel=1e-13)[0]
    assert b == pytest.approx(want, rel=1e-10)
    assert _line(light, *args, 0.5, 0.9) == 0.0


def test_unit_normal_is_the_normalised_cross_product_or_any_perpendicular():
    n = kernels.unit_normal(0.0, 2.0, 0.0, 0.0, 0.0, 1.0, 1e-12)
    assert n == pytest.approx((1.0, 0.0, 0.0))
    for d in ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0)):        # a along d: some unit vector ⊥ d
        n = np.array(kernels.unit_normal(*d, *d, 1e-12))
        assert np.linalg.norm(n) == pytest.approx(1.0) and abs(n @ d) < 1e-15


@pytest.mark.parametrize("src, sign", [((1.0, 0.0, 0.0), 1.0), ((0.0, 1.0, 0.0), -1.0)])
def test_camera_stokes_rotates_by_twice_the_scattering_plane_angle(src, sign):
    """Ray +z, camera r = x, u = y: source along x puts e_par on r (no change), along y on u (2β = π)."""
    dirs = np.array([[0.0, 0.0, 1.0]])
    q_out, u_out = np.zeros(1), np.zeros(1)
    kernels.camera_stokes(np.array(src), np.zeros(3), dirs, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                          Stokes(np.ones(1), np.array([0.3]), np.array([0.2]), np.zeros(1)), q_out, u_out)
    assert (q_out[0], u_out[0]) == pytest.approx((sign * 0.3, sign * 0.2), abs=1e-15)


def test_clip_rays_to_half_spaces():
    """Half-spaces z ≥ 0 and x ≤ 0.5 (planes through the apex (0.5, 0, 0)) along rays from (0, 0, −1)."""
    origin = np.array([[0.0, 0.0, -1.0]])
    d45 = np.array([1.0, 0.0, 1.0]) / math.sqrt(2)
    dirs = np.array([[0.0, 0.0, 1.0], d45, [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    lo, hi = np.empty(4), np.empty(4)
    normals = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
    kernels.clip_rays(origin, dirs, np.zeros(4), np.full(4, 5.0), np.array([0.5, 0.0, 0.0]), normals, 1e-13,
                      lo, hi)
    assert (lo[0], hi[0]) == (1.0, 5.0)                      # enters z ≥ 0 at z = 0
    assert (lo[1], hi[1]) == pytest.approx((math.sqrt(2), 0.5 * math.sqrt(2)))  # z ≥ 0 only after x > 0.5
    assert hi[2] == -math.inf                                # parallel to z = 0 and below it: dropped whole
    assert hi[3] < lo[3]                                     # going away from z ≥ 0


def test_direct_kernel_closed_form_with_the_source_outside_the_box():
    """D = ρ cos φ/π · I0 e^{−σ_t(ℓ_LO + ℓ_CO)}/(d² + r_s²), ℓ only inside the box, 0 where unlit."""
    src = np.array([[0.0, 0.0, -3.0]])
    cam = np.array([0.0, 0.0, -2.0])
    pts = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5]])
    nrm = np.array([[0.0, 0.6, -0.8], [0.0, 0.6, -0.8]])
    out = np.empty(2)
    light = Light(src, 0.01, 2.0, False, np.zeros((0, 3)))
    kernels.direct_kernel(light, Medium(0.5, 0.0, BOX_LO, BOX_HI), cam,
                          SurfacePoints(pts, nrm, np.array([0.4, 0.4]), np.array([True, False])), out)
    want = 0.4 * 0.8 / math.pi * 2.0 * math.exp(-0.5 * (1.5 + 1.5)) / (3.5 ** 2 + 0.01 ** 2)
    assert out[0] == pytest.approx(want, rel=1e-14)
    assert out[1] == 0.0
