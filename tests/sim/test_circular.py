"""Circular light (docs/physics.md §5.1): the Mueller matrix's m44, the quarter-wave plates on the source
and the analyzer, V through single scattering and the retention factors, against closed forms, Jones
calculus and brute-force quadrature written here."""

import math

import numpy as np
import pytest
from polarstripe.sim.mitsuba_polarized import mueller_elements
from polarstripe.sim.patterns import parse_pattern
from polarstripe.sim.polarization import (
    analyzer,
    cone_retention,
    least_backscatter_angle,
    pair_retention,
    rayleigh_m44,
    rayleigh_mueller,
)
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import SceneError, load_scene, scene_from_dict
from polarstripe.sim.transport import line_radiance, make_source
from scipy.integrate import quad

DELTA = 0.2


# --------------------------------------------------------------------------- Jones calculus, written here

def _jones_stokes(ex, ey):
    """Stokes (I, Q, U, V) of a Jones vector in a frame (x, y, k) right-handed about the light's direction;
    V = 2·Im(E_x E_y*): with the quarter-wave plate diag(1, i) in its fast-axis frame, a polarizer along x
    and the plate at +45° give V = +1 (the convention of Mitsuba's ``linear_retarder``)."""
    return np.array([abs(ex) ** 2 + abs(ey) ** 2, abs(ex) ** 2 - abs(ey) ** 2, 2 * (ex * np.conj(ey)).real,
                     2 * (ex * np.conj(ey)).imag])


def _qwp(angle):
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, s], [-s, c]])                       # into the fast-axis frame
    return rot.T @ np.diag([1.0, 1j]) @ rot


def _mueller_from_jones(j):
    """M = A (J ⊗ J*) A⁻¹ with the Stokes convention of :func:`_jones_stokes`."""
    basis = [np.array(v, complex) for v in ((1, 0), (0, 1), (1, 1), (1, 1j))]
    cols = []
    for e in basis:                                          # a spanning set of pure states
        cols.append((_jones_stokes(*e), _jones_stokes(*(j @ e))))
    s_in = np.array([c[0] for c in cols]).T
    s_out = np.array([c[1] for c in cols]).T
    return s_out @ np.linalg.inv(s_in)


def test_jones_convention_is_mitsubas():
    """Polarizer along x, quarter-wave plate at +45°: V = +1 (Mitsuba's linear_retarder rotated by 45°)."""
    s = _jones_stokes(*(_qwp(math.pi / 4) @ np.array([1.0, 0.0])))
    np.testing.assert_allclose(s, [1, 0, 0, 1], atol=1e-12)


# ---------------------------------------------------------------------------------------------- m44

def test_m44_of_depolarized_rayleigh():
    """Hansen & Travis: m44 = Δ·Δ'·(3/2)μ with Δ' = (1 − 2δ)/(1 − δ); m44/m11 = ±(1 − 2δ) at 0 and π, and
    m44(π) = m11(π) − 2·m22(π) (randomly oriented mirror-symmetric particles); δ = 0 is Rayleigh's
    m44 = m33."""
    for d in (0.0, 0.1, 0.2, 0.35):
        big, big2 = (1 - d) / (1 + d / 2), (1 - 2 * d) / (1 - d)
        mu = np.linspace(-1, 1, 11)
        np.testing.assert_allclose(rayleigh_m44(1 - mu, 1 + mu, d), big * big2 * 1.5 * mu, rtol=1e-12)
        m11, _, m22, m33 = rayleigh_mueller(np.array([0.0, 2.0]), np.array([2.0, 0.0]), d)
        m44 = rayleigh_m44(np.array([0.0, 2.0]), np.array([2.0, 0.0]), d)
        np.testing.assert_allclose(m44 / m11, [1 - 2 * d, -(1 - 2 * d)], rtol=1e-12)
        assert m44[1] == pytest.approx(m11[1] - 2 * m22[1], rel=1e-12)
        if d == 0:
            np.testing.assert_allclose(rayleigh_m44(1 - mu, 1 + mu, d),
                                       rayleigh_mueller(1 - mu, 1 + mu, d)[3])


def test_truth_phase_function_carries_the_same_m44():
    mu = np.linspace(-1, 1, 21)
    p = np.full_like(mu, 0.3)
    m11, *_, m44 = mueller_elements(mu, p, DELTA)
    r11 = rayleigh_mueller(1 - mu, 1 + mu, DELTA)[0]
    np.testing.assert_allclose(m44, p * rayleigh_m44(1 - mu, 1 + mu, DELTA) / r11, rtol=1e-12)


def test_circular_cone_retention():
    """r_cV = ∫_cone P·m44/m11 dω ÷ ∫_cone P dω: 1 − 2δ for a cone of width → 0, and the isotropic cone's
    by scipy quadrature; circular light keeps less than linear light in every cone (δ > 0)."""
    cos_c = math.cos(math.radians(30))
    narrow = cone_retention(lambda a, b: np.where(a < 1e-6, 1.0, 0.0), cos_c, DELTA, circular=True)
    assert narrow == pytest.approx(1 - 2 * DELTA, abs=1e-6)

    def ratio(mu):
        return rayleigh_m44(1 - mu, 1 + mu, DELTA) / rayleigh_mueller(1 - mu, 1 + mu, DELTA)[0]

    want = quad(ratio, cos_c, 1.0)[0] / (1 - cos_c)
    iso = cone_retention(lambda a, b: np.full(np.shape(a), 0.25 / math.pi), cos_c, DELTA, circular=True)
    assert iso == pytest.approx(want, rel=1e-4)
    assert iso < cone_retention(lambda a, b: np.full(np.shape(a), 0.25 / math.pi), cos_c, DELTA)


def _full_mueller(mu, d):
    m11, m12, m22, m33 = rayleigh_mueller(1 - mu, 1 + mu, d)
    m44 = rayleigh_m44(1 - mu, 1 + mu, d)
    return np.array([[m11, m12, 0, 0], [m12, m22, 0, 0], [0, 0, m33, 0], [0, 0, 0, m44]])


def _normalised(mu):
    m = _full_mueller(mu, DELTA)
    return m / m[0, 0]


def _rotator(angle):
    c, s = math.cos(2 * angle), math.sin(2 * angle)
    return np.array([[1, 0, 0, 0], [0, c, s, 0], [0, -s, c, 0], [0, 0, 0, 1]])


def test_circular_pair_retention_against_explicit_mueller_products():
    """κ_V of isotropic scattering: circular light along +z scattered at ω then back to −z, 4×4 Mueller
    matrices P·M_R/m11_R (P = 1/4π) with explicit frame rotations, summed over a Gauss–Legendre ×
    uniform-azimuth grid; ÷ the
    once-backscattered V (m44/m11 at π). Both flip the helicity, so κ_V > 0."""
    nt, nphi = 48, 48
    t, w = np.polynomial.legendre.leggauss(nt)
    v_sum = i_sum = 0.0
    for mu1, wt in zip(t, w, strict=True):
        for k in range(nphi):
            phi = (k + 0.5) * 2 * math.pi / nphi
            # first scattering +z → ω(θ1, φ): plane through z and ω; rotate the incident frame (x, y) by φ
            s = _normalised(mu1) @ _rotator(phi) @ np.array([1.0, 0, 0, 1.0])
            # second: ω → −z, scattering angle cos = −mu1, in the same plane (no rotation between: the plane
            # through ω and −z is the plane through z and ω)
            s = _normalised(-mu1) @ s
            v_sum += wt * s[3]
            i_sum += wt * s[0]
    once = rayleigh_m44(2.0, 0.0, DELTA) / rayleigh_mueller(2.0, 0.0, DELTA)[0]
    want = v_sum / i_sum / once
    got = pair_retention(lambda a, b: np.full(np.shape(a), 0.25 / math.pi), DELTA, circular=True)
    assert got == pytest.approx(want, abs=2e-3)
    assert 0 < got < 1


# --------------------------------------------------------------------------- the source and single scattering

def _circular_scene(source_qw=45.0, camera_qw=None, res=(33, 33)):
    s = load_scene(None)
    pol = s.projector.polarization.replace(quarter_wave_deg=source_qw)
    return s.replace(projector=s.projector.replace(polarization=pol),
                     camera=s.camera.replace(resolution=res, polarizer=s.camera.polarizer.replace(
                         quarter_wave_deg=camera_qw)))


def test_scene_keys():
    pol = {"dop": 1.0, "angle_deg": 90.0, "quarter_wave_deg": 45}
    s = scene_from_dict({"projector": {"polarization": pol},
                         "camera": {"polarizer": {"quarter_wave_deg": 135.0}}})
    assert s.projector.polarization.quarter_wave_deg == 45.0
    assert s.camera.polarizer.quarter_wave_deg == 135.0
    assert load_scene(None).projector.polarization.quarter_wave_deg is None
    with pytest.raises(SceneError, match="projector.polarization.quarter_wave_deg"):
        scene_from_dict({"projector": {"polarization": {"quarter_wave_deg": "x"}}})
    with pytest.raises(SceneError, match="camera.polarizer.quarter_wave_deg"):
        scene_from_dict({"camera": {"polarizer": {"quarter_wave_deg": float("nan")}}})


@pytest.mark.parametrize("angle, qw", [(90.0, 45.0), (90.0, 135.0), (90.0, 60.0), (30.0, 100.0), (0.0, 0.0)])
def test_source_state_is_jones(angle, qw):
    """The source's (L, V) on its axis (transport.Source.linear_circular) is Jones calculus of the polarizer
    and the plate in a frame right-handed about the projector's forward axis."""
    scene = _circular_scene(qw)
    pol = scene.projector.polarization.replace(angle_deg=angle)
    src = make_source(scene.replace(projector=scene.projector.replace(polarization=pol)),
                      parse_pattern("flood"))
    # (x, y, k) = (u, r, f) is right-handed (r × u = −f): angles from r toward u are angles from y toward x
    e = np.array([math.sin(math.radians(angle)), math.cos(math.radians(angle))], complex)
    fast = math.pi / 2 - math.radians(qw)
    s = _jones_stokes(*(_qwp(fast) @ e))
    lin, v = src.linear_circular
    assert v == pytest.approx(s[3], abs=1e-12)
    assert abs(lin) == pytest.approx(math.hypot(s[1], s[2]), abs=1e-12)


def test_straight_back_the_helicity_flips_by_one_minus_two_delta():
    """A point source just behind the camera on its axis: every node of the axis pixel scatters straight back
    (μ = −1), so V/B = m44/m11(π)·V_L = −(1 − 2δ)·V_L and no linear polarization (m12(π) = 0, V_L = ±1)."""
    for qw, v_l in ((45.0, 1.0), (135.0, -1.0)):
        s = _circular_scene(qw)
        s = s.replace(projector=s.projector.replace(model="point", position=(0.0, 0.0, -0.01), up=(0, 1, 0),
                                                    look_at=(0.0, 0.0, 0.38)))
        c = render_components(s, "flood", "standard", pixels=np.array([[16, 16]]), need=("B", "p"),
                              orders="single")
        assert c.v[0] == pytest.approx(-(1 - 2 * DELTA) * v_l, abs=1e-6)
        assert c.dolp[0] < 1e-6


def test_single_scattering_against_jones_and_brute_force_quadrature():
    """One ray, by scipy quadrature: at each point Y the source's state is Jones calculus of the polarizer
    and the plate (each axis projected ⊥ the light, in the scattering plane's frame), the intensity
    σ_s P·(1 + m12/m11·Q_in)·e^{−σ_t(ℓ_L + ℓ_C)}/d² and V = m44/m11·V_in of it; the kernel's B and its
    B-weighted v sum within 0.3 %, with the helicity flipped."""
    from polarstripe.sim.geometry import segment_length_in_box
    from polarstripe.sim.phase import evaluate

    s = _circular_scene(45.0)
    src = make_source(s, parse_pattern("flood"))
    cam = np.array(s.camera.position, float)
    d = np.array([0.1, 0.05, 1.0])
    d /= np.linalg.norm(d)
    lo, hi = np.asarray(src.box_lo), np.asarray(src.box_hi)
    x1 = float(np.min(np.where(d > 0, (hi - cam) / np.where(d > 0, d, 1), np.inf)))
    b, q, u, v = line_radiance(src, cam, d[None], np.zeros(1), (np.zeros(1, np.int64), np.zeros(1),
                                                                 np.array([x1])), 64, polarization=True)

    def integrand(x, which):
        y = cam + x * d
        k_in = y - src.position
        dist = np.linalg.norm(k_in)
        k_in /= dist
        mu = float(k_in @ -d)
        e_perp = np.cross(k_in, -d)
        e_perp /= np.linalg.norm(e_perp)
        e_par = np.cross(e_perp, k_in)                   # (e_par, e_perp, k_in) right-handed
        e = np.array([src.e_field @ e_par, src.e_field @ e_perp], complex)
        fast = math.atan2(src.fast_axis @ e_perp, src.fast_axis @ e_par)
        st = _jones_stokes(*(_qwp(fast) @ e))
        st /= st[0]
        m = _full_mueller(mu, DELTA)
        p = float(evaluate(s.medium.phase, np.array([1 - mu]), np.array([1 + mu]))[0]) / m[0, 0]
        ell = float(segment_length_in_box(src.position, y[None], lo, hi)[0]) + x
        base = s.medium.sigma_s * p * math.exp(-s.medium.sigma_t * ell) / (dist ** 2 + src.radius ** 2)
        return base * (m @ st)[0 if which == "b" else 3]

    want_b = quad(integrand, 0.0, x1, args=("b",), limit=200)[0]
    want_v = quad(integrand, 0.0, x1, args=("v",), limit=200)[0]
    assert b[0] == pytest.approx(want_b, rel=3e-3)
    assert v[0] == pytest.approx(want_v, rel=3e-3)
    assert v[0] < 0 < src.linear_circular[1]          # the helicity flips


# ------------------------------------------------------------------------------------------- the analyzer

@pytest.mark.parametrize("alpha, phi", [(45.0, 0.0), (45.0, 90.0), (30.0, 100.0), (0.0, 20.0)])
def test_analyzer_with_a_quarter_wave_plate_is_the_mueller_product(alpha, phi):
    """Through a plate at α then an ideal polarizer at φ: the first row of P(φ)·QWP(α) (from Jones calculus)
    applied to (B, Bq, Bu, Bv) in the camera frame, plus the unpolarized object light / 2."""
    c = render_components(_circular_scene(45.0, alpha, (9, 7)), "flood", "preview", orders="single")
    mq = _mueller_from_jones(_qwp(math.radians(alpha)))
    pol = 0.5 * np.array([1, math.cos(2 * math.radians(phi)), math.sin(2 * math.radians(phi)), 0])
    row = pol @ mq
    stokes = np.stack([c.B, c.Bq, c.Bu, c.Bv])
    want = 0.5 * (c.D + c.A) + np.tensordot(row, stokes, axes=1)
    np.testing.assert_allclose(analyzer(c, phi, extinction_ratio=np.inf), want, rtol=1e-10)


def test_a_circular_analyzer_finds_the_flipped_helicity():
    """Source polarizer at 90°, plate at 45°: V_L = +1, and the backscatter's V < 0 (flipped). With the
    camera's plate at α = 45° the rotating analyzer passes V > 0 at φ = α + 45° = 90° and V < 0 at 0°, so
    the least backscatter is at about 90° (its linear U shifts it a little)."""
    c = render_components(_circular_scene(45.0, 45.0, (16, 12)), "flood", "standard", orders="single")
    assert np.all(c.v < 0)
    ang = least_backscatter_angle(c)
    assert ang == pytest.approx(90.0, abs=12.0)
    e_90, e_0 = (analyzer(c, a, extinction_ratio=np.inf) for a in (90.0, 0.0))
    assert np.all(e_90 < e_0)


def test_constant_dop_model_flips_the_helicity():
    """``dop = {model = "constant", p}``: the backscatter carries p times the source's state with the helicity
    flipped, every order (docs/physics.md §5.1): V/B = −p·V_L, no linear part for circular light."""
    s = _circular_scene(45.0, None, (8, 6))
    s = s.replace(medium=s.medium.replace(dop=s.medium.dop.replace(model="constant", p=0.7)))
    for orders in ("single", "all"):
        c = render_components(s, "flood", "preview", need=("B", "p"), orders=orders)
        np.testing.assert_allclose(c.v, -0.7, atol=1e-12)
        assert np.all(c.dolp < 1e-12)
