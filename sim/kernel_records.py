"""The compiled kernels' arguments, bundled by kind (:mod:`polarstripe.sim.kernels`,
:mod:`polarstripe.sim.transport`).

Module-level NamedTuples are plain tuples to numba: free to pass, and ``cache=True`` keeps working.
:mod:`polarstripe.sim.transport` builds them with fixed field types (float64 / int64 / bool, C-contiguous
arrays), so each kernel compiles once. Records passed into a function called in an inner loop hold scalars
only (:class:`PhaseArgs`): a record holding an array costs a reference count per call.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Light(NamedTuple):
    """The source as the line integral sees it."""

    position: np.ndarray        # (1, 3) shared or (n, 3) one per ray
    radius: float               # r_s [m]
    intensity: float            # I0 [W/sr]
    inside: bool                # inside (or on) the medium box: the exact truncation applies
    facing: np.ndarray          # (0, 3) none, (1, 3) or (n, 3): normals of a surface point "source" (A)


class Medium(NamedTuple):
    """Extinction and scattering coefficients [1/m] and the medium box."""

    sigma_t: float
    sigma_s: float
    box_lo: np.ndarray          # (3,)
    box_hi: np.ndarray          # (3,)


class PhaseArgs(NamedTuple):
    """The phase function: code 0 isotropic, 1 HG(g1), 2 TTHG α·HG(g1) + (1 − α)·HG(−g2), 3 the similarity
    scaled P̃: α·HG(g1) + (1 − α)·HG(−g2) times ``norm`` where 1 − μ ≥ ``cut``, 0 inside the forward cone
    (:mod:`polarstripe.sim.similarity`), 4 that phase function inside the cone only (1 − μ < ``cut``).
    Scalars only, so passing it to :func:`phase_value` in the inner loop costs nothing."""

    code: int
    g1: float
    g2: float
    alpha: float
    cut: float = 0.0
    norm: float = 1.0


class Quadrature(NamedTuple):
    """How each interval is cut and summed: Gauss–Legendre rules of n = (nodes, nodes/2, nodes/4) points
    padded into (3, nodes) ``t``/``w``, the polarization node subsets ``subs`` (3, 5) of each rule (``nsubs``
    (3,) long), the phase function's forward-lobe width [rad] and the scattering angles [rad] where intervals
    are split."""

    nodes: int
    t: np.ndarray
    w: np.ndarray
    n: np.ndarray
    subs: np.ndarray
    nsubs: np.ndarray
    width: float
    split_alphas: np.ndarray


class Polarization(NamedTuple):
    """Whether to accumulate the Stokes sums (``on``); whether the intensity scattered from the polarized
    source takes the Mueller matrix's m12·Q (``mueller``: the Rayleigh-δ model with DOP_L > 0); whether the
    rays run from the source and ``Light`` is the receiver (``reversed``: A's beams); the source's unit
    E-field (3,), its DOP and the medium's δ (docs/physics.md §5); ``dsigma`` ≥ 0 the extra extinction of
    the polarized part of the light in the Stokes sums (σ_p − σ̃_t, docs/physics.md §10.4; else 0); the
    fast axis (3,) of a quarter-wave plate after the source's polarizer (zeros: none; docs/physics.md §5.1)
    and ``dsigma_v``, the circular part's extra extinction (σ_pV − σ̃_t)."""

    on: bool
    mueller: bool
    reversed: bool
    e_field: np.ndarray
    dop_l: float
    depol: float
    dsigma: float = 0.0
    fast_axis: np.ndarray = np.zeros(3)
    dsigma_v: float = 0.0


class Rays(NamedTuple):
    """View rays origin + x·dirs; the view path enters the medium at x = view_start."""

    origin: np.ndarray          # (1, 3) shared or (n, 3)
    dirs: np.ndarray            # (n, 3) unit
    view_start: np.ndarray      # (n,)


class Intervals(NamedTuple):
    """Lit intervals [lo, hi] of ray index ``ray`` (from :func:`polarstripe.sim.patterns.lit_intervals`)."""

    ray: np.ndarray             # (m,) int64
    lo: np.ndarray
    hi: np.ndarray


class Stokes(NamedTuple):
    """Per-ray radiance b and its B-weighted Stokes sums q, u (linear) and v (circular), each (n,)."""

    b: np.ndarray
    q: np.ndarray
    u: np.ndarray
    v: np.ndarray


class SurfacePoints(NamedTuple):
    """Surface points (m, 3), unit normals (m, 3), albedo (m,) and whether the pattern lights them (m,)."""

    points: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    lit: np.ndarray
