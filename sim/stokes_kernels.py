"""The source's Stokes vector and the Mueller matrix's m12 at one quadrature node, compiled (numba): the small
pieces :func:`polarstripe.sim.kernels.line_integrals` calls per node (docs/physics.md §5, §5.1)."""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True)
def m12_over_m11(omm, opm, big):
    """m12/m11 of the Rayleigh-δ reduced matrix (docs/physics.md §5): −Δ·¾(1 − μ²) / (Δ·¾(1 + μ²) + 1 − Δ)."""
    mu = 0.5 * (opm - omm)
    return -big * 0.75 * (omm * opm) / (big * 0.75 * (1.0 + mu * mu) + 1.0 - big)


@njit(cache=True, nogil=True)
def source_state(aa, bb, af, bf, qwp):
    """Unit Stokes (q, u, v) of the source light in the scattering-plane frame (docs/physics.md §5.1): a
    linear polarizer whose E-field has components aa in the plane and bb normal to it (ψ_E = atan2(bb, aa)),
    then, with ``qwp``, a quarter-wave plate whose fast axis has components (af, bf) (ψ_F): linear
    cos 2(ψ_E − ψ_F) along the fast axis and v = sin 2(ψ_F − ψ_E) (Mitsuba's retarder convention). Zeros
    where the field has no component ⊥ the light."""
    nrm = aa * aa + bb * bb
    if nrm <= 0:
        return 0.0, 0.0, 0.0
    if not qwp:
        return (aa * aa - bb * bb) / nrm, 2.0 * aa * bb / nrm, 0.0
    nf = af * af + bf * bf
    if nf <= 0:
        return 0.0, 0.0, 0.0
    c, s = aa * af + bb * bf, bb * af - aa * bf          # ∝ cos, sin of ψ_E − ψ_F
    cs = c * c + s * s
    c2d, s2d = (c * c - s * s) / cs, 2.0 * c * s / cs
    return c2d * (af * af - bf * bf) / nf, c2d * 2.0 * af * bf / nf, -s2d
