"""The similarity (δ-truncation) split of the phase function that the higher orders of scattering rest on.

Light scattered within the forward cone θ_s < θ_c keeps going (almost) where it went: for where the energy
goes it is not scattered at all, only its path is blurred. Cutting that cone out of the phase function P gives
the similarity-scaled medium (Wiscombe's δ-M truncation with Nakajima & Tanaka's exact single-scattering
correction; docs/physics.md §10):

    f = ∫_{θ_s<θ_c} P dω,   σ̃_s = (1 − f) σ_s,   σ̃_t = σ_t − f σ_s,   P̃ = P·[θ_s ≥ θ_c] / (1 − f)

so σ̃_s P̃ = σ_s P at every wide angle and only the cone's extinction is given back. In the scaled medium the
unscattered light is the "quasi-direct" light (direct plus forward-scattered), once-scattered light is exact
single scattering with P at wide angles, and the orders beyond converge fast (σ̃_s ≈ 0.2 σ_s for the paper's
TTHG 0.8). θ_c = 30°: checked against Monte Carlo, the scaled medium reproduces the all-orders image of the
paper's tank to a few per cent for cones of 10–35°; wider cones bend too much light (−18 % at 60°, HG 0.8).

The mean cosine g̃ of P̃ (what the grid of :mod:`polarstripe.sim.multiple` keeps of its anisotropy) and the
cone's mean square polar angle ⟨θ²⟩ (the width of the blur, :mod:`polarstripe.sim.psf`) come with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from polarstripe.sim.phase import tthg_parameters
from polarstripe.sim.scene import Medium, Phase

THETA_C = math.radians(30.0)


@dataclass(frozen=True)
class TruncatedPhase:
    """The phase function P̃ of the scaled medium: ``base`` (a scene :class:`Phase`) with its forward cone
    θ_s < θ_c removed and the rest divided by 1 − f (``norm`` = 1/(1 − f)). The transport kernels read it
    through :func:`polarstripe.sim.transport._phase_code` (code 3)."""

    base: Phase
    cos_c: float
    norm: float
    model: str = "truncated"
    cone: bool = False           # True: the cone alone, P·[θ_s < θ_c] (unnormalised; code 4)

    @property
    def g(self) -> float:
        return self.base.g


@dataclass(frozen=True)
class Scaled:
    """The similarity-scaled medium: f, σ̃_t, σ̃_s [1/m], P̃ and its mean cosine g̃, and the forward cone's
    per-axis mean square angle θ²_x = ⟨θ²⟩/2 [rad²] (the blur)."""

    f: float
    sigma_t: float
    sigma_s: float
    phase: TruncatedPhase
    g_tilde: float
    theta2_x: float


def _hg_base(phase: Phase) -> tuple[float, float, float]:
    """(g1, g2, α) with P = α HG(g1) + (1 − α) HG(−g2) (an isotropic phase is HG(0))."""
    if phase.model == "isotropic":
        return 0.0, 0.0, 1.0
    if phase.model == "hg":
        return float(phase.g), 0.0, 1.0
    gf, gb, alpha = tthg_parameters(float(phase.g))
    if alpha == 0.0:
        return 0.0, 0.0, 1.0
    return gf, gb, alpha


def _hg_outside(g: float, cos_c: float) -> tuple[float, float]:
    """∫ over μ < cos_c of HG(g) dω and of μ·HG(g) dω (closed forms; g clamped to |g| ≤ 1 − 10⁻⁶)."""
    g = min(max(g, -1 + 1e-6), 1 - 1e-6)
    if abs(g) < 1e-9:
        return 0.5 * (1 + cos_c), 0.25 * (cos_c * cos_c - 1.0)
    a, b = 1 + g * g, 2 * g
    c = (1 - g * g) / 2.0

    def s(mu):          # 1/√(a − bμ)
        return 1.0 / math.sqrt(a - b * mu)

    mass = c / b * 2 * (s(cos_c) - s(-1.0))
    # ∫ μ (a − bμ)^{-3/2} dμ = 2(a − bμ/2... ) : with v = a − bμ, μ = (a − v)/b, dμ = −dv/b
    def prim(mu):
        v = a - b * mu
        return (2 * a / math.sqrt(v) + 2 * math.sqrt(v)) / (b * b)
    first = c * (prim(cos_c) - prim(-1.0))
    return mass, first


@lru_cache(maxsize=64)
def _truncation(model: str, g: float, theta_c: float) -> tuple[float, float, float]:
    """(f, g̃, ⟨θ²⟩ inside the cone) of a scene phase function cut at θ_c."""
    g1, g2, alpha = _hg_base(Phase(model, g) if model != "isotropic" else Phase("isotropic", 0.0))
    cos_c = math.cos(theta_c)
    m1, f1 = _hg_outside(g1, cos_c)
    m2, f2 = _hg_outside(-g2, cos_c)
    outside = alpha * m1 + (1 - alpha) * m2
    first = alpha * f1 + (1 - alpha) * f2
    f = min(max(1.0 - outside, 0.0), 1.0)
    g_t = first / outside if outside > 0 else 0.0
    # ⟨θ²⟩ over the cone: Gauss–Legendre in θ on graded pieces (the HG peak is ~1 − g wide)
    edges = np.unique(np.clip(np.array([0.0, 0.3, 1.0, 3.0, 9.0, 27.0]) * max(1 - abs(g1), 1e-3), 0, theta_c))
    edges = np.append(edges, theta_c) if edges[-1] < theta_c else edges
    t, w = np.polynomial.legendre.leggauss(24)
    num = den = 0.0
    for a0, a1 in zip(edges[:-1], edges[1:], strict=True):
        th = 0.5 * (a1 + a0) + 0.5 * (a1 - a0) * t
        mu = np.cos(th)
        p = alpha * _hg(mu, g1) + (1 - alpha) * _hg(mu, -g2)
        wt = 0.5 * (a1 - a0) * w * 2 * np.pi * np.sin(th) * p
        num += float((wt * th * th).sum())
        den += float(wt.sum())
    theta2 = num / den if den > 0 else 0.0
    return f, g_t, theta2


def _hg(mu, g):
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * mu) ** 1.5)


def scaled_medium(medium: Medium, theta_c: float = THETA_C) -> Scaled:
    """The similarity-scaled medium of ``medium`` (module docstring): f, σ̃_t, σ̃_s, P̃, g̃, θ²_x.

    Parameters
    ----------
    medium : the scene's Medium (σ_t [1/m], albedo, phase).
    theta_c : the forward cone's half angle [rad], in (0, π/2].

    Returns
    -------
    Scaled; σ̃_t = σ_t − f σ_s ≥ σ_a and σ̃_s/σ̃_t ≤ the albedo.
    """
    from polarstripe.sim.scene import SceneError

    if not (isinstance(theta_c, (int, float)) and 0.0 < float(theta_c) <= math.pi / 2):
        raise SceneError(f"similarity cone theta_c must be in (0, pi/2] rad, got {theta_c!r}")
    ph = medium.phase
    f, g_t, theta2 = _truncation(ph.model, float(ph.g), float(theta_c))
    sig_s = medium.sigma_s
    st = max(medium.sigma_t - f * sig_s, 0.0)
    norm = 1.0 / (1.0 - f) if f < 1.0 else 0.0
    return Scaled(f, st, (1.0 - f) * sig_s, TruncatedPhase(ph, math.cos(theta_c), norm), g_t, 0.5 * theta2)


def truncated_code(phase: TruncatedPhase) -> tuple[int, float, float, float, float, float]:
    """The transport kernel's phase arguments of P̃: (3, g1, g2, α, 1 − cos θ_c, 1/(1 − f)); of the cone
    alone (``phase.cone``): (4, g1, g2, α, 1 − cos θ_c, 1)."""
    g1, g2, alpha = _hg_base(phase.base)
    if phase.cone:
        return 4, g1, g2, alpha, 1.0 - phase.cos_c, 1.0
    return 3, g1, g2, alpha, 1.0 - phase.cos_c, phase.norm


def truncated_value(phase: TruncatedPhase, one_minus_mu, one_plus_mu) -> np.ndarray:
    """P̃ [1/sr] (numpy): the base phase function times 1/(1 − f) outside the cone, 0 inside."""
    from polarstripe.sim.phase import evaluate

    omm = np.asarray(one_minus_mu, float)
    val = evaluate(phase.base, omm, np.asarray(one_plus_mu, float)) * phase.norm
    return np.where(omm < 1.0 - phase.cos_c, 0.0, val)


@lru_cache(maxsize=64)
def pair_retention_of(model: str, g: float, depolarization: float, circular: bool = False) -> float:
    """κ (``circular``: κ_V) of :func:`polarstripe.sim.polarization.pair_retention` for the scaled P̃ of a
    scene phase function."""
    from polarstripe.sim.polarization import pair_retention

    ph = scaled_medium(Medium(sigma_t=1.0, albedo=1.0, phase=Phase(model, g))).phase
    return pair_retention(lambda a, b: truncated_value(ph, a, b), depolarization, circular=circular)


@lru_cache(maxsize=64)
def cone_retention_of(model: str, g: float, depolarization: float, circular: bool = False) -> float:
    """r_c (``circular``: r_cV) of :func:`polarstripe.sim.polarization.cone_retention` for a scene phase
    function's cone."""
    from polarstripe.sim.phase import evaluate
    from polarstripe.sim.polarization import cone_retention

    ph = Phase(model, g)
    return cone_retention(lambda a, b: evaluate(ph, a, b), math.cos(THETA_C), depolarization,
                          circular=circular)


def polarized_extinction(scaled: Scaled, sigma_s: float, model: str, g: float,
                         depolarization: float, circular: bool = False) -> float:
    """σ_p = σ̃_t + (1 − r_c)·f·σ_s [1/m]: the extinction of the polarized part of the light (docs/physics.md
    §10.4). The quasi-direct light is a Poisson sum over cone scatterings (rate f·σ_s),
    e^{−σ_t ℓ}·Σ_n (fσ_sℓ)ⁿ/n!; each scattering keeps r_c of the polarization, so its polarized part sums
    to e^{−σ_t ℓ + r_c f σ_s ℓ} = e^{−σ_p ℓ}. ``circular``: σ_pV with r_cV (docs/physics.md §5.1)."""
    r_c = cone_retention_of(model, float(g), float(depolarization), bool(circular))
    return float(scaled.sigma_t + (1.0 - r_c) * scaled.f * float(sigma_s))
