"""Polarization: the depolarized-Rayleigh Mueller model of the backscatter DOP and the linear analyzer.

Mueller model (paper appendix eq. 15; docs/physics.md §5): Hansen & Travis' depolarized Rayleigh reduced
matrix with depolarization factor δ, in the scattering-plane frame with Q = I_∥ − I_⊥ (Bohren–Huffman).
The medium's Mueller matrix is the phase function times this matrix normalised by its m11, so light
scattered from a polarized source has intensity P·(1 + m12/m11·Q_in) (docs/physics.md §5). δ = 0.2 gives
DOP_B = 0.8 at backscatter. Circular light: m44, the quarter-wave plates and V (docs/physics.md §5.1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from polarstripe.heap import shared_zeros
from polarstripe.sim.sensor_kernels import malus, malus_basis


def rayleigh_mueller(one_minus_mu, one_plus_mu, depolarization: float):
    """Reduced Mueller elements (m11, m12 = m21, m22, m33) of depolarized Rayleigh scattering.

    Δ = (1 − δ)/(1 + δ/2);  m11 = Δ·¾(1 + μ²) + 1 − Δ;  m12 = −Δ·¾(1 − μ²);  m22 = Δ·¾(1 + μ²);
    m33 = Δ·(3/2)·μ.  Inputs are 1 − μ and 1 + μ (μ = cos θ_s) so that 1 − μ² keeps its precision.
    """
    d = float(depolarization)
    big = (1.0 - d) / (1.0 + d / 2.0)
    omm, opm = np.asarray(one_minus_mu, float), np.asarray(one_plus_mu, float)
    mu = 0.5 * (opm - omm)
    sin2 = omm * opm
    m22 = big * 0.75 * (1.0 + mu * mu)
    return m22 + (1.0 - big), -big * 0.75 * sin2, m22, big * 1.5 * mu


def rayleigh_m44(one_minus_mu, one_plus_mu, depolarization: float):
    """m44 of the depolarized-Rayleigh reduced matrix (Hansen & Travis 1974; m34 = 0), in the units of
    :func:`rayleigh_mueller`: m44 = Δ·Δ'·(3/2)·μ, Δ' = (1 − 2δ)/(1 − δ), so Δ·Δ' = (1 − 2δ)/(1 + δ/2).
    m44/m11 = ±(1 − 2δ) at θ = 0 and π (0.6 for δ = 0.2, against m22/m11 = 1 − δ = 0.8), negative
    backwards: the helicity flips (the identity m44(π) = m11(π) − 2·m22(π) of randomly oriented
    mirror-symmetric particles holds)."""
    d = float(depolarization)
    mu = 0.5 * (np.asarray(one_plus_mu, float) - np.asarray(one_minus_mu, float))
    return (1.0 - 2.0 * d) / (1.0 + d / 2.0) * 1.5 * mu


def dop_backscatter(theta_s_rad, dop_l: float = 1.0, psi_rad: float = np.pi / 2, depolarization: float = 0.2):
    """DOP of singly scattered light vs scattering angle (paper eq. 15 generalised; Fig. 11).

    Parameters
    ----------
    theta_s_rad : array, scattering angle [rad] (π = backscatter).
    dop_l : source degree of polarization.
    psi_rad : angle between the source polarization and the scattering plane [rad] (π/2: perpendicular).
    depolarization : δ.

    Returns
    -------
    DOP in [0, 1], same shape as ``theta_s_rad``.
    """
    th = np.asarray(theta_s_rad, float)
    m11, m12, m22, m33 = rayleigh_mueller(1.0 - np.cos(th), 1.0 + np.cos(th), depolarization)
    q_in, u_in = dop_l * np.cos(2 * psi_rad), dop_l * np.sin(2 * psi_rad)
    i_out = m11 + m12 * q_in
    return np.hypot(m12 + m22 * q_in, m33 * u_in) / i_out


def polarizer_transmittances(extinction_ratio: float) -> tuple[float, float]:
    """Principal transmittances (k1, k2) of a real linear polarizer: k1 = 1, k2 = 1/extinction_ratio."""
    return 1.0, 1.0 / float(extinction_ratio)


@dataclass(frozen=True)
class AnalyzerBasis:
    """What the radiance through a linear analyzer needs that does not depend on its angle: ``total`` =
    D + A + B and the polarized part on the analyzer's circle, ``q`` = B·p·cos 2χ + Sq and
    ``u`` = B·p·sin 2χ + Su (the backscatter's, and the object's behind a camera port; flat arrays of the
    components' ``shape``), and the analyzer's principal
    transmittances k1, k2. A scan keeps one per pattern: its second analyzer angle costs one pass
    (:func:`through_analyzer`)."""

    total: np.ndarray
    q: np.ndarray
    u: np.ndarray
    k1: float
    k2: float
    shape: tuple[int, ...]


def analyzer_basis(components, extinction_ratio: float | None = None) -> AnalyzerBasis:
    """The angle-free part of :func:`analyzer` (docs/physics.md §4.1): B·p·cos 2(φ − χ) = q cos 2φ + u sin 2φ
    with (q, u) = B·p·(cos 2χ, sin 2χ) = B·p·(Q, U)/√(Q² + U²), (Q, U) the backscatter's Stokes on the
    analyzer's circle (``components.seen_stokes``), p = ``components.p`` as it is (clipped to [0, 1], 0 where
    B = 0) and (q, u) = 0 where Q = U = 0. The extinction ratio defaults to the scene's."""
    er = components.scene.camera.polarizer.extinction_ratio if extinction_ratio is None else extinction_ratio
    k1, k2 = polarizer_transmittances(er)
    flat = [np.ascontiguousarray(a, dtype=float).reshape(-1) for a in
            (components.D, components.A, components.B, *components.seen_stokes())]
    total, q, u = (np.empty(flat[0].size) for _ in range(3))
    malus_basis(*flat, total, q, u)          # one compiled pass (sim/sensor_kernels.py)
    if _nonzero(components.Sq) or _nonzero(components.Su):  # the object's light polarized by a camera port
        sq, su = components.object_seen_stokes()
        q += np.ravel(sq)
        u += np.ravel(su)
    return AnalyzerBasis(total, q, u, float(k1), float(k2), tuple(np.shape(components.B)))


def _nonzero(a: np.ndarray) -> bool:
    """Whether ``a`` has a nonzero item; False at once for the shared zeros (polarstripe.heap), which a
    render without a camera port gives for Sq and Su."""
    return a is not shared_zeros(np.shape(a)) and bool(np.any(a))


def through_analyzer(basis: AnalyzerBasis, angle_deg: float) -> np.ndarray:
    """Radiance through the analyzer at ``angle_deg``, shape ``basis.shape``: ½(k1 + k2)·total +
    ½(k1 − k2)·(q cos 2φ + u sin 2φ), one compiled pass (sim/sensor_kernels.py)."""
    two_phi = 2.0 * np.radians(float(angle_deg))
    out = np.empty(basis.total.size)
    malus(basis.total, basis.q, basis.u, 0.5 * (basis.k1 + basis.k2), 0.5 * (basis.k1 - basis.k2),
          float(np.cos(two_phi)), float(np.sin(two_phi)), out)
    return out.reshape(basis.shape)


def analyzer(components, angle_deg: float | None, extinction_ratio: float | None = None) -> np.ndarray:
    """Radiance [W sr⁻¹ m⁻²] through a linear analyzer at ``angle_deg`` (Malus; paper eqs. 4–5).

    I(φ) = ½(k1 + k2)(D + A + B) + ½(k1 − k2)·[B·p·cos 2(φ − χ) + Sq cos 2φ + Su sin 2φ]: object light
    unpolarized (Sq = Su = 0) but behind a camera port's diattenuation (docs/physics.md §11), backscatter with
    DOP p and angle χ (``components.p``, ``components.chi_rad``, camera frame: from image right toward
    image up). With a quarter-wave plate at α in front of the analyzer (``camera.polarizer.quarter_wave_deg``)
    p and χ are the effective ones, √(Q_α² + V²)/B and α + ½ atan2(V, Q_α), and this is the Mueller product
    of the plate and the polarizer (docs/physics.md §5.1). ``angle_deg=None`` means no analyzer (nor plate):
    D + A + B. The extinction ratio defaults to the scene's. Computed as
    ``through_analyzer(analyzer_basis(components), angle_deg)``: the cosine expanded, equal to the formula
    above to rounding (a few ulp of B·p).
    """
    if angle_deg is None:
        return components.D + components.A + components.B
    return through_analyzer(analyzer_basis(components, extinction_ratio), angle_deg)


def least_backscatter_angle(components, mask: np.ndarray | None = None) -> float:
    """The one analyzer angle [deg, in [0, 180)] that passes the least backscatter over the image.

    From the B-weighted Stokes sums Σ B p (cos 2χ, sin 2χ) (optionally over ``mask``): the angle crossed to
    the mean backscatter polarization. Per pixel it is χ + 90°.
    """
    w = components.B * components.p
    if mask is not None:
        w = np.where(mask, w, 0.0)
    chi = components.chi_rad
    s1, s2 = float(np.sum(w * np.cos(2 * chi))), float(np.sum(w * np.sin(2 * chi)))
    return float((np.degrees(0.5 * np.arctan2(s2, s1)) + 90.0) % 180.0)


def _stokes_scatter(kin, kout, ref, q, u, depolarization, v=0.0):
    """Vectorised: Stokes (q, u, v) of unit-intensity light along kin (reference axis ``ref`` ⊥ kin)
    after one scattering into kout with the reduced Mueller model; returns (q', u', ref', gain, v') in kout's
    frame, gain the intensity (m11 + m12·q_in)/m11 of the matrix normalised by its m11 (docs/physics.md §5)
    and v' = m44·v/(m11 + m12·q_in)."""
    mu = (kin * kout).sum(-1)
    n = np.cross(kin, kout)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    fallback = np.cross(kin, np.where(np.abs(kin[..., :1]) < 0.9, [1.0, 0, 0], [0, 1.0, 0]))
    e_perp = np.where(nn > 1e-12, n / np.maximum(nn, 1e-300), fallback / np.linalg.norm(fallback, axis=-1,
                                                                                          keepdims=True))
    e_par_in = np.cross(e_perp, kin)
    ang = np.arctan2((np.cross(ref, e_par_in) * kin).sum(-1), (ref * e_par_in).sum(-1))
    c2, s2 = np.cos(2 * ang), np.sin(2 * ang)
    qi, ui = q * c2 + u * s2, -q * s2 + u * c2
    m11, m12, m22, m33 = rayleigh_mueller(1 - mu, 1 + mu, depolarization)
    i = m11 + m12 * qi
    v_out = rayleigh_m44(1 - mu, 1 + mu, depolarization) * v / i
    return (m12 + m22 * qi) / i, m33 * ui / i, np.cross(e_perp, kout), i / m11, v_out


def pair_retention(phase_value, depolarization: float, nodes: int = 6000, circular: bool = False) -> float:
    """κ: how much of the single-scatter DOP light keeps after one more wide-angle scattering.

    Light along +z, polarized along y, is scattered twice back to −z through every intermediate direction ω
    (a Fibonacci sphere of ``nodes`` points), each scattering with the Mueller matrix P·M_R/m11_R of
    docs/physics.md §5 (:func:`rayleigh_mueller`; the m12 term included, so a path's intensity depends on the
    polarization it carries), P the phase function ``phase_value(1 − μ, 1 + μ)`` (the scaled P̃ of
    docs/physics.md §10); κ = DOP(sum of the twice-scattered Stokes) ÷ DOP of once-backscattered light
    (1 − δ). The default tank gives κ ≈ 0.65; isotropic scattering 0.54.

    ``circular``: the same for light circularly polarized (V = 1): κ_V = V of the twice-scattered sum ÷ V of
    once-backscattered light (m44/m11 at π, < 0: both flip the helicity, so κ_V > 0; docs/physics.md §5.1).
    """
    k = np.arange(nodes) + 0.5
    z = 1 - 2 * k / nodes
    r = np.sqrt(np.maximum(1 - z * z, 0.0))
    a = np.pi * (1 + 5 ** 0.5) * k
    w = np.stack([r * np.cos(a), r * np.sin(a), z], 1)
    kin = np.broadcast_to([0.0, 0.0, 1.0], w.shape)
    kout = np.broadcast_to([0.0, 0.0, -1.0], w.shape)
    weight = phase_value(1 - w[:, 2], 1 + w[:, 2]) * phase_value(1 + w[:, 2], 1 - w[:, 2])
    if not np.any(weight > 0):
        return 0.0
    q0, v0 = (np.zeros(nodes), np.ones(nodes)) if circular else (np.ones(nodes), np.zeros(nodes))
    qa, ua, ra, ga, va = _stokes_scatter(kin, w, np.broadcast_to([0.0, 1.0, 0.0], w.shape), q0,
                                         np.zeros(nodes), depolarization, v0)
    qb, ub, rb, gb, vb = _stokes_scatter(w, kout, ra, qa, ua, depolarization, va)
    weight = weight * ga * gb
    if circular:
        once = rayleigh_m44(2.0, 0.0, depolarization) / rayleigh_mueller(2.0, 0.0, depolarization)[0]
        return float((weight * vb).sum() / weight.sum() / once) if once != 0 else 0.0
    ref = np.broadcast_to([1.0, 0.0, 0.0], w.shape)
    ang = np.arctan2((np.cross(ref, rb) * kout).sum(-1), (ref * rb).sum(-1))
    q = qb * np.cos(2 * ang) - ub * np.sin(2 * ang)
    u = qb * np.sin(2 * ang) + ub * np.cos(2 * ang)
    dop2 = np.hypot((weight * q).sum(), (weight * u).sum()) / weight.sum()
    return float(dop2 / (1.0 - float(depolarization))) if depolarization < 1 else 0.0


def cone_retention(phase_value, cos_c: float, depolarization: float, nodes: int = 4000,
                   circular: bool = False) -> float:
    """r_c: the fraction of its linear polarization light keeps in one scattering inside the forward cone.

    Scattering by θ at a uniform azimuth turns linear Stokes (Q, U) about the axis into ½(m22 + m33)/m11 of
    themselves on average (the m12 and cos 4φ terms average out), so r_c = ∫_cone P·½(m22 + m33)/m11 dω ÷
    ∫_cone P dω over θ < θ_c (cos θ_c = ``cos_c``), P = ``phase_value(1 − μ, 1 + μ)`` (docs/physics.md
    §10.4); 1 − δ at θ = 0. Nodes are uniform in log(1 − μ) from 10⁻¹² (a forward peak of HG g → 1).
    ``circular``: r_cV = ∫_cone P·m44/m11 dω ÷ ∫_cone P dω (V is the same in every frame about the axis;
    1 − 2δ at θ = 0: 0.6 for δ = 0.2, below linear light's 1 − δ = 0.8, docs/physics.md §5.1).
    """
    x = np.geomspace(1e-12, 1.0 - float(cos_c), int(nodes))     # x = 1 − μ
    m11, _, m22, m33 = rayleigh_mueller(x, 2.0 - x, depolarization)
    keep = rayleigh_m44(x, 2.0 - x, depolarization) if circular else 0.5 * (m22 + m33)
    p = phase_value(x, 2.0 - x) * x                               # dμ = x d(log x)
    return float(np.trapezoid(p * keep / m11, np.log(x)) / np.trapezoid(p, np.log(x)))
