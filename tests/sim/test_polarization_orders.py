"""The polarization the higher orders keep (docs/physics.md §10.4): κ per further wide-angle scattering and
r_c per scattering in the forward cone, against independent computations."""

import math

import numpy as np
import pytest
from polarstripe.sim.phase import evaluate
from polarstripe.sim.polarization import cone_retention, pair_retention
from polarstripe.sim.scene import Medium, Phase
from polarstripe.sim.similarity import THETA_C, polarized_extinction, scaled_medium, truncated_value


def _mueller(kin, kout, d):
    """3×3 linear block of P-free M_R/m11_R (I, Q, U) between frames with basis n × k (n = kin × kout)."""
    mu = (kin * kout).sum(-1)
    n = np.cross(kin, kout)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    big = (1 - d) / (1 + d / 2)
    m11 = big * 0.75 * (1 + mu * mu) + 1 - big
    m = np.zeros(mu.shape + (3, 3))
    m[..., 0, 0] = 1
    m[..., 0, 1] = m[..., 1, 0] = -big * 0.75 * (1 - mu * mu) / m11
    m[..., 1, 1] = big * 0.75 * (1 + mu * mu) / m11
    m[..., 2, 2] = big * 1.5 * mu / m11
    return m, np.cross(n, kin), np.cross(n, kout)


def _rotation(k, e_from, e_to):
    """Stokes (I, Q, U) in basis e_from re-expressed in basis e_to (both ⊥ k), right-handed about k."""
    a = np.arctan2((np.cross(e_from, e_to) * k).sum(-1), (e_from * e_to).sum(-1))
    r = np.zeros(a.shape + (3, 3))
    r[..., 0, 0] = 1
    r[..., 1, 1] = r[..., 2, 2] = np.cos(2 * a)
    r[..., 1, 2], r[..., 2, 1] = np.sin(2 * a), -np.sin(2 * a)
    return r


def _brute_pair(p, d, n=40000):
    """Twice-scattered Stokes by matrix products on random intermediate directions (seeded)."""
    rng = np.random.default_rng(3)
    w = rng.normal(size=(n, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    kin, kout, ex = (np.broadcast_to(v, w.shape) for v in ([0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]))
    m1, a_in, a_out = _mueller(kin, w, d)
    m2, b_in, b_out = _mueller(w, kout, d)
    s = np.einsum("nij,j->ni", _rotation(kin, ex, a_in), [1.0, -1.0, 0.0])       # polarized along y
    s = np.einsum("nij,nj->ni", m1, s)
    s = np.einsum("nij,nj->ni", _rotation(w, a_out, b_in), s)
    s = np.einsum("nij,nj->ni", m2, s)
    s = np.einsum("nij,nj->ni", _rotation(kout, b_out, ex), s)
    tot = ((p(w[:, 2]) * p(-w[:, 2]))[:, None] * s).sum(0)
    return math.hypot(tot[1], tot[2]) / tot[0] / (1 - d)


@pytest.mark.parametrize("model,g", [("isotropic", 0.0), ("tthg", 0.8), ("hg", 0.5)])
def test_pair_retention_is_the_mueller_product(model, g):
    """κ (Fibonacci quadrature, per-event normalised Stokes times intensity gains) equals the DOP of the
    summed matrix products M_R2·R·M_R1 over random intermediate directions, m12 included."""
    ph = scaled_medium(Medium(phase=Phase(model, g))).phase

    def p(mu):
        return truncated_value(ph, 1 - mu, 1 + mu)

    kappa = pair_retention(lambda a, b: truncated_value(ph, a, b), 0.2)
    assert kappa == pytest.approx(_brute_pair(p, 0.2), abs=0.02)


def test_pair_retention_limits():
    """Without depolarization and with only near-backscatter, light keeps all its polarization."""
    def back(omm, opm):
        return np.where(np.asarray(opm) < 1e-3, 1.0, 0.0) + np.where(np.asarray(omm) < 1e-3, 1.0, 0.0)

    assert pair_retention(back, 0.0, nodes=200000) == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize("delta", [0.0, 0.2, 0.4])
def test_cone_retention_limits(delta):
    """r_c → 1 − δ for a cone of vanishing width (m22 = m33 = (1 − δ)m11 at θ = 0); for an isotropic cone
    of 30° it is the solid-angle mean of ½(m22 + m33)/m11, by plain quadrature in μ."""
    narrow = cone_retention(lambda a, b: evaluate(Phase("hg", 0.999999), a, b), math.cos(THETA_C), delta)
    assert narrow == pytest.approx(1 - delta, abs=2e-3)
    big = (1 - delta) / (1 + delta / 2)
    mu = np.linspace(math.cos(THETA_C), 1, 20001)
    r = big * 0.75 * (1 + mu * mu + 2 * mu) / 2 / (big * 0.75 * (1 + mu * mu) + 1 - big)
    iso = cone_retention(lambda a, b: np.full(np.shape(a), 0.25 / math.pi), math.cos(THETA_C), delta)
    assert iso == pytest.approx(float(np.trapezoid(r, mu) / (1 - math.cos(THETA_C))), abs=1e-4)


def test_polarized_extinction_adds_the_cone_loss():
    """σ_p = σ̃_t + (1 − r_c) f σ_s; for TTHG 0.8 the cone keeps a little under 1 − δ per scattering (its
    wider angles turn the plane a little), and with δ = 0 almost all (pure Rayleigh: ½(1 + μ)²/(1 + μ²))."""
    med = Medium(sigma_t=5.0, albedo=1.0)
    sc = scaled_medium(med)
    r0 = 1 - (polarized_extinction(sc, med.sigma_s, "tthg", 0.8, 0.0) - sc.sigma_t) / (sc.f * med.sigma_s)
    r2 = 1 - (polarized_extinction(sc, med.sigma_s, "tthg", 0.8, 0.2) - sc.sigma_t) / (sc.f * med.sigma_s)
    assert 0.98 < r0 < 1.0 and 0.75 < r2 < 0.8
