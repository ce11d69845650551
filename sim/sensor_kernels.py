"""A frame's per-pixel passes after the model, compiled (numba): the analyzer's Malus sum and its angle-free
part, and the EMVA 1288 sensor in one pass, draws included (docs/physics.md §4.1, §7).

Each pass reads every pixel once and writes it once, where numpy needs one pass (and one temporary) per
operation. The sensor's draws come from the pixel's own window of a counter-based stream
(sim/counter_rng.py), so a band of pixels can be exposed on any thread and the frame is the same. The
passes release the GIL.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from polarstripe.sim.counter_rng import normal, pixel_key, splitmix, unit

POISSON_EXACT_BELOW = 30.0   # mean electrons below which shot noise is drawn by inversion (docs/physics.md §7)
_RECIPROCALS = 1.0 / np.maximum(np.arange(128.0), 1.0)   # 1/k: the inversion's recursion without a division


@njit(cache=True, nogil=True)
def malus(total, q, u, a, b, c, s, out):
    """out = a·total + b·(q·c + u·s) over flat arrays: the radiance through a linear analyzer at φ with
    a = ½(k1 + k2), b = ½(k1 − k2), c = cos 2φ, s = sin 2φ (:func:`polarstripe.sim.polarization.analyzer`)."""
    for i in range(out.size):
        out[i] = a * total[i] + b * (q[i] * c + u[i] * s)


@njit(cache=True, nogil=True)
def malus_basis(d, a, b, sq, su, total, q, u):
    """The analyzer's angle-free part over flat arrays: total = D + A + B and (q, u) = B·p·(Q, U)/√(Q² + U²)
    with p = clip(√(Q² + U²)/B, 0, 1) (0 where B ≤ 0) and (q, u) = 0 where Q = U = 0: the operations of
    :attr:`polarstripe.sim.render.Components.p` and :func:`polarstripe.sim.polarization.analyzer_basis`."""
    for i in range(total.size):
        bi = b[i]
        total[i] = d[i] + a[i] + bi
        norm = math.hypot(sq[i], su[i])
        if norm > 0.0:
            p = min(max(norm / bi, 0.0), 1.0) if bi > 0.0 else 0.0
            scale = bi * p / norm
        else:
            scale = 0.0
        q[i] = scale * sq[i]
        u[i] = scale * su[i]


@njit(inline="always")
def poisson_count(lam, key, n):
    """A Poisson(λ) count as a float, from the draws ``n``, ``n + 1``, … of ``key``: inversion below
    :data:`POISSON_EXACT_BELOW` (exact), above it a normal z through the rounded Cornish–Fisher expansion
    λ + √λ·z + (z² − 1)/6 − z(2 + z²)/(72√λ) (docs/physics.md §7)."""
    if lam < POISSON_EXACT_BELOW:
        u = unit(splitmix(key, n))
        p = math.exp(-lam)
        f, k = p, 0
        while u > f and p > 1e-17 and k < 127:   # past the mode, terms below 1e-17 cannot move f
            k += 1
            p *= lam * _RECIPROCALS[k]
            f += p
        return float(k)
    z = normal(key, n)[0]
    r = math.sqrt(lam)
    x = lam + r * z + (z * z - 1.0) * (1.0 / 6.0) - z * (2.0 + z * z) / (72.0 * r)
    return max(math.floor(x + 0.5), 0.0)


@njit(cache=True, nogil=True)
def expose_pixels(radiance, e_map, dark_e, key, first, read_e, full_well, inv_gain, offset, top, gaussian,
                  out):
    """The EMVA 1288 sensor over flat arrays whose item j is pixel ``first + j`` (uint16 ``out``):
    μ = min(max(L, 0)·e + μ_dark, 1e12) (NaN and +inf radiance read as 0); electrons Poisson(μ) capped at the
    full well plus σ_r·z (``gaussian``: μ + √(μ + σ_r²)·z capped at the full well); y = clip(rint(e/K +
    offset), 0, top) with ``inv_gain`` = 1/K. Draws: the read noise's normal, then the shot noise's, from the
    pixel's own sequence."""
    for j in range(out.size):
        x = radiance[j]
        if not x > 0.0 or x == np.inf:
            x = 0.0
        lam = min(x * e_map[j] + dark_e, 1e12)
        own = pixel_key(key, first + j)
        z, n = normal(own, np.uint64(0))
        if gaussian:
            e = min(lam + math.sqrt(lam + read_e * read_e) * z, full_well)
        else:
            e = min(poisson_count(lam, own, n), full_well) + read_e * z
        out[j] = min(max(np.rint(e * inv_gain + offset), 0.0), top)
