"""A frame's per-pixel passes after the model, compiled (numba): the analyzer's Malus sum and the EMVA 1288
sensor's arithmetic around its random draws (docs/physics.md §5.1, §7).

Each pass reads every pixel once and writes it once, where numpy needs one pass (and one temporary) per
operation. The sensor's passes do the same floating-point operations in the same order as the numpy
expressions they replace (:func:`polarstripe.sim.sensor.expose`), so a frame is bit-identical; the draws
themselves stay numpy's (``rng.poisson``, ``rng.normal``, ``rng.standard_normal``), so a seed gives the same
noise. They release the GIL: frames can be exposed on several threads at once.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def malus(total, q, u, a, b, c, s, out):
    """out = a·total + b·(q·c + u·s) over flat arrays: the radiance through a linear analyzer at φ with
    a = ½(k1 + k2), b = ½(k1 − k2), c = cos 2φ, s = sin 2φ (:func:`polarstripe.sim.polarization.analyzer`)."""
    for i in range(out.size):
        out[i] = a * total[i] + b * (q[i] * c + u[i] * s)


@njit(cache=True, nogil=True)
def mean_electrons(radiance, e_map, dark_e, out):
    """out = min(max(L, 0)·e + μ_dark, 1e12) with NaN and +inf radiance read as 0 (flat arrays)."""
    for i in range(out.size):
        x = radiance[i]
        if np.isnan(x) or x == np.inf:
            x = 0.0
        elif x < 0.0:
            x = 0.0
        out[i] = min(x * e_map[i] + dark_e, 1e12)


@njit(cache=True, nogil=True)
def digitize(shot, read, full_well, gain, offset, top, out):
    """out = clip(rint((min(shot, full well) + read)/K + offset), 0, top) as uint16 (flat arrays): the
    electrons of the Poisson draw ``shot`` capped at the full well, the read noise ``read`` added, the ADC."""
    for i in range(out.size):
        y = np.rint((min(float(shot[i]), full_well) + read[i]) / gain + offset)
        out[i] = min(max(y, 0.0), top)


@njit(cache=True, nogil=True)
def gaussian_dn(radiance, e_map, dark_e, read_var, z, full_well, inv_gain, offset, top, out):
    """The Gaussian sensor in float32 (flat arrays; ``z`` standard normal draws): μ = clip(L·e, 0, 1e12) +
    μ_dark with NaN and +inf as 0, e = min(μ + z·√(μ + σ_r²), full well), y = clip(rint(e/K + offset), 0,
    top) as uint16."""
    for i in range(out.size):
        lam = np.float32(radiance[i]) * np.float32(e_map[i])
        if np.isnan(lam) or lam == np.inf:
            lam = np.float32(0.0)
        lam = min(max(lam, np.float32(0.0)), np.float32(1e12)) + dark_e
        e = z[i] * np.sqrt(lam + read_var) + lam
        e = min(e, full_well) * inv_gain + offset
        out[i] = min(max(np.rint(e), np.float32(0.0)), top)
