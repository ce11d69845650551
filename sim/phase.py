"""Phase functions normalised per steradian: Haltrin's TTHG by mean cosine, single HG, isotropic.

All evaluators take (1 − μ) and (1 + μ) separately (μ = cos θ_s, θ_s = 0 forward) so that the HG denominators
(1 − g)² + 2g(1 − μ) stay exact near μ = ±1 when |g| → 1 (docs/physics.md §1).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from polarstripe.sim.scene import Phase
from scipy.optimize import brentq

_G_MAX = 1.0 - 1e-6


def hg(one_minus_mu: np.ndarray, one_plus_mu: np.ndarray, g: float) -> np.ndarray:
    """Henyey–Greenstein phase function p_HG(μ; g) [1/sr], stable for |g| → 1.

    p_HG = (1 − g²) / (4π (1 + g² − 2gμ)^{3/2}); the denominator is written (1−g)² + 2g(1−μ) for g ≥ 0
    and (1+g)² − 2g(1+μ) for g < 0, both sums of non-negative terms.
    """
    g = float(np.clip(g, -_G_MAX, _G_MAX))
    if g >= 0:
        den = (1.0 - g) ** 2 + 2.0 * g * np.maximum(one_minus_mu, 0.0)
    else:
        den = (1.0 + g) ** 2 - 2.0 * g * np.maximum(one_plus_mu, 0.0)
    return (1.0 - g) * (1.0 + g) / (4.0 * np.pi * den * np.sqrt(den))


@lru_cache(maxsize=64)
def tthg_parameters(mean_cosine: float) -> tuple[float, float, float]:
    """Haltrin's one-parameter closure: (g_F, g_B, α) for a mean cosine g ∈ [0, 1).

    g_B = −0.30614 + 1.0006 g_F − 0.01826 g_F² + 0.03644 g_F³,
    α = g_B(1 + g_B)/((g_F + g_B)(1 + g_B − g_F)),  g = g_F g_B/(1 + g_B − g_F) solved for g_F by brentq.
    """
    g = float(mean_cosine)

    def gb_of(gf):
        return -0.30614 + 1.0006 * gf - 0.01826 * gf ** 2 + 0.03644 * gf ** 3

    lo = brentq(gb_of, 0.2, 0.5, xtol=1e-15)  # g_F where g_B = 0 (isotropic end)
    if g <= 1e-12:                             # isotropic to within 1e-12
        return lo, 0.0, 0.0
    g = min(g, _G_MAX)

    def mean(gf):
        gb = gb_of(gf)
        return gf * gb / (1.0 + gb - gf) - g

    a = lo
    while mean(a) >= 0:                        # step off the root of g_B (round-off at tiny g)
        a += 1e-12
    # the closure's largest mean cosine (g_F = 1 − 10⁻⁶) is a hair below 1 − 10⁻⁶: clamp g there
    gf = _G_MAX if mean(_G_MAX) <= 0 else brentq(mean, a, _G_MAX, xtol=1e-15, rtol=1e-15, maxiter=200)
    gb = gb_of(gf)
    alpha = gb * (1.0 + gb) / ((gf + gb) * (1.0 + gb - gf))
    return gf, gb, alpha


def tthg(one_minus_mu: np.ndarray, one_plus_mu: np.ndarray, mean_cosine: float) -> np.ndarray:
    """Haltrin's two-term HG, P = α p_HG(μ; g_F) + (1 − α) p_HG(μ; −g_B) [1/sr] (paper ref. [8])."""
    gf, gb, alpha = tthg_parameters(float(mean_cosine))
    if alpha == 0.0:
        return np.full(np.shape(one_minus_mu), 1.0 / (4.0 * np.pi))
    return alpha * hg(one_minus_mu, one_plus_mu, gf) + (1.0 - alpha) * hg(one_minus_mu, one_plus_mu, -gb)


def evaluate(phase: Phase, one_minus_mu: np.ndarray, one_plus_mu: np.ndarray) -> np.ndarray:
    """P(θ_s) [1/sr] of a scene's phase model, given 1 − cos θ_s and 1 + cos θ_s."""
    if phase.model == "isotropic":
        return np.full(np.shape(one_minus_mu), 1.0 / (4.0 * np.pi))
    if phase.model == "hg":
        return hg(one_minus_mu, one_plus_mu, phase.g)
    return tthg(one_minus_mu, one_plus_mu, phase.g)

