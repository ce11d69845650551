"""A frame's per-pixel passes after the model, compiled (numba): the analyzer's Malus sum and its angle-free
part, and the EMVA 1288 sensor in one pass, draws included (docs/physics.md §4.1, §7).

Each pass reads every pixel once and writes it once, where numpy needs one pass (and one temporary) per
operation; the sensor takes the frame in chunks of 1024 pixels, each step of a chunk one loop (those that
vectorize apart from the draws that branch). The sensor's draws come from the pixel's own window of a
counter-based stream (sim/counter_rng.py), so a band of pixels can be exposed on any thread and the frame
is the same. The passes release the GIL.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from polarstripe.sim.counter_rng import normal, own_seed, pixel_normals, splitmix, unit
from polarstripe.sim.frame_kernels import stokes_norm

POISSON_EXACT_BELOW = 30.0   # mean e⁻ below which shot noise is drawn exactly (docs/physics.md §7)
_RECIPROCALS = 1.0 / np.maximum(np.arange(128.0), 1.0)   # 1/k: the inversion's recursion without a division
_PAIR_RECIPROCALS = 1.0 / ((np.arange(128.0) + 1.0) * (np.arange(128.0) + 2.0))   # 1/((k + 1)(k + 2))
_ONE = np.uint64(1)
_STEPS_PER_E = 8      # the tabulated means λ₀ = j/8 e⁻ below POISSON_EXACT_BELOW (a power of two: 8λ exact)
_BUCKETS = 64         # the guide tables' buckets of u (a power of two: u·64 is exact)


def _poisson_tables(steps: int, buckets: int, width: int = 96):
    """The CDFs F(k) = Σ_{j≤k} e^{−λ₀}λ₀^j/j!, k < ``width``, of the means λ₀ = row/``steps`` below
    POISSON_EXACT_BELOW (the last set to 1: F(95) rounds to 1 there, the tail past it is below 10⁻¹⁸), and
    their guide tables: the least k with F(k) ≥ j/``buckets``, j = 0 … ``buckets``."""
    lam0 = np.arange(1, int(POISSON_EXACT_BELOW * steps))[:, None] / steps
    k = np.arange(width)
    log_pmf = -lam0 + k * np.log(lam0) - np.array([math.lgamma(x + 1.0) for x in k])
    cdf = np.minimum(np.cumsum(np.exp(log_pmf), axis=1), 1.0)
    cdf = np.vstack([np.ones(width), cdf])                    # λ₀ = 0: the count is 0
    cdf[:, -1] = 1.0
    guide = np.array([np.searchsorted(row, np.arange(buckets + 1) / buckets) for row in cdf], np.int64)
    return cdf, guide


_CDF, _GUIDE = _poisson_tables(_STEPS_PER_E, _BUCKETS)


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
    :attr:`polarstripe.sim.render.Components.p` and :func:`polarstripe.sim.polarization.analyzer_basis`
    (√(Q² + U²) by :func:`~polarstripe.sim.frame_kernels.stokes_norm`: equal to hypot's to an ulp)."""
    for i in range(total.size):
        bi = b[i]
        total[i] = d[i] + a[i] + bi
        norm = stokes_norm(sq[i], su[i])
        if norm > 0.0:
            p = min(max(norm / bi, 0.0), 1.0) if bi > 0.0 else 0.0
            scale = bi * p / norm
        else:
            scale = 0.0
        q[i] = scale * sq[i]
        u[i] = scale * su[i]


@njit(nogil=True)
def _poisson_inversion(lam, u):
    """An exact Poisson(λ) count by inversion of the uniform ``u`` (a call of its own): the least k with
    u ≤ F(k), the pmf's terms two at a time (p_{k+2} = p_k·λ²/((k+1)(k+2)) beside p_{k+1}, so the sum's chain
    takes one add per two terms)."""
    p = math.exp(-lam)
    if u <= p:
        return 0.0
    f, k = p, 0
    lam2 = lam * lam
    while p > 1e-17 and k < 126:                  # past the mode, terms below 1e-17 cannot move f
        p1 = p * (lam * _RECIPROCALS[k + 1])
        p = p * (lam2 * _PAIR_RECIPROCALS[k])
        f1 = f + p1
        f = f + (p1 + p)
        if u <= f:
            return float(k + 1) if u <= f1 else float(k + 2)
        k += 2
    return float(k)


@njit(inline="always")
def _poisson_by_table(lam, key, n):
    """An exact Poisson(λ) count for λ < 30 from the words ``n`` and ``n + 1`` of ``key``, as the sum of two
    independent counts (Poisson(λ₀) + Poisson(λ − λ₀) is Poisson(λ)): one of mean λ₀ = ⌊Sλ⌋/S from its
    tabulated CDF, entered at its guide table's bucket (Chen & Asau 1974), and one of mean f = λ − λ₀ < 1/S,
    0 without the exponential when u ≤ 1 − f ≤ e^{−f}, else by :func:`_poisson_inversion`."""
    row = int(lam * _STEPS_PER_E)
    u = unit(splitmix(key, n))
    k = _GUIDE[row, int(u * _BUCKETS)]
    while u > _CDF[row, k]:
        k += 1
    f = lam - row * (1.0 / _STEPS_PER_E)
    u = unit(splitmix(key, n + _ONE))
    if u <= 1.0 - f:
        return float(k)
    return float(k) + _poisson_inversion(f, u)


@njit(inline="always")
def poisson_count(lam, key, n):
    """A Poisson(λ) count as a float, from the draws ``n``, ``n + 1``, … of ``key``: exact below
    :data:`POISSON_EXACT_BELOW` (:func:`_poisson_by_table`), above it a normal z through the rounded
    Cornish–Fisher expansion λ + √λ·z + (z² − 1)/6 − z(2 + z²)/(72√λ) (docs/physics.md §7)."""
    if lam < POISSON_EXACT_BELOW:
        return _poisson_by_table(lam, key, n)
    z = normal(key, n)[0]
    r = math.sqrt(lam)
    x = lam + r * z + (z * z - 1.0) * (1.0 / 6.0) - z * (2.0 + z * z) / (72.0 * r)
    return max(np.rint(x), 0.0)                   # rint: ties (probability 0) to even


_CHUNK = 1024        # pixels whose means, normals and DN are each made in one loop that vectorizes


@njit(inline="always")
def _mean_electrons(radiance, e_map, dark_e, start, buf):
    """buf[k] = min(max(L, 0)·e + μ_dark, 1e12) for the pixels start + k (NaN and +inf radiance read as 0);
    how many (up to the buffer's size)."""
    m = min(buf.size, radiance.size - start)
    for k in range(m):
        x = radiance[start + k]
        buf[k] = min((x if 0.0 < x < np.inf else 0.0) * e_map[start + k] + dark_e, 1e12)
    return m


@njit(inline="always")
def _to_dn(e, m, inv_gain, offset, top, out, start):
    """out[start + k] = clip(rint(e[k]/K + offset), 0, top) for k < m (uint16 ``out``)."""
    for k in range(m):
        out[start + k] = min(max(np.rint(e[k] * inv_gain + offset), 0.0), top)


@njit(cache=True, nogil=True)
def expose_poisson(radiance, e_map, dark_e, keys, first, read_e, full_well, inv_gain, offset, top, out):
    """The EMVA 1288 sensor over flat arrays whose item j is pixel ``first + j`` (uint16 ``out``): μ of
    :func:`_mean_electrons`, electrons min(Poisson(μ), full well) + σ_r·z, y = clip(rint(e/K + offset), 0,
    top) with ``inv_gain`` = 1/K. Draws (``keys``: the frame's two, sim/counter_rng.py): the read noise's
    normal (the pixel's first word), then the shot noise's count from the pixel's own sequence."""
    lam, z, e = np.empty(_CHUNK), np.empty(_CHUNK), np.empty(_CHUNK)
    n, seeds = np.empty(_CHUNK, np.uint64), np.empty(_CHUNK, np.uint64)
    for start in range(0, out.size, _CHUNK):
        m = _mean_electrons(radiance, e_map, dark_e, start, lam)
        pixel_normals(keys, first + start, z[:m], n[:m])
        for k in range(m):
            seeds[k] = own_seed(keys, first + start + k)
        for k in range(m):
            e[k] = min(poisson_count(lam[k], seeds[k], n[k]), full_well) + read_e * z[k]
        _to_dn(e, m, inv_gain, offset, top, out, start)


@njit(cache=True, nogil=True)
def expose_gaussian(radiance, e_map, dark_e, keys, first, read_e, full_well, inv_gain, offset, top, out):
    """As :func:`expose_poisson` with shot and read noise as one normal: e = min(μ + √(μ + σ_r²)·z, full
    well), z the pixel's first normal."""
    lam, z, n = np.empty(_CHUNK), np.empty(_CHUNK), np.empty(_CHUNK, np.uint64)
    read_var = read_e * read_e
    for start in range(0, out.size, _CHUNK):
        m = _mean_electrons(radiance, e_map, dark_e, start, lam)
        pixel_normals(keys, first + start, z[:m], n[:m])
        for k in range(m):
            lam[k] = min(lam[k] + math.sqrt(lam[k] + read_var) * z[k], full_well)
        _to_dn(lam, m, inv_gain, offset, top, out, start)
