"""Compiled (numba) per-pixel passes of whole frames in :mod:`polarstripe.sim.higher`: the P1 irradiance of
the grid's field at the pixels' object points, and the orders ≥ 2 added to the backscatter's Stokes. Each
replaces numpy arithmetic with the same operations in the same order, one pass instead of several
temporaries (a 640×480 frame is 307 200 pixels: each numpy pass over it costs about a millisecond)."""

from __future__ import annotations

import math

from numba import njit
from polarstripe.sim.grid_kernels import _axis


@njit(cache=True, nogil=True)
def field_irradiance(grid, phi, flux, points, normals, out):
    """out[m] = max(0, φ/4 − F·n/2) at ``points`` (m, 3) with outward ``normals`` (m, 3): the P1 irradiance
    of the field (φ, F) sampled trilinearly (as :func:`~polarstripe.sim.grid_kernels.sample_fields`)."""
    lo, h, n = grid
    for m in range(points.shape[0]):  # sample_fields' loop, written out: a shared per-point helper, even
        i0, tx = _axis(points[m, 0], lo[0], h[0], n[0])  # inline="always", cost 2x here (measured)
        j0, ty = _axis(points[m, 1], lo[1], h[1], n[1])
        k0, tz = _axis(points[m, 2], lo[2], h[2], n[2])
        p = 0.0
        f0 = f1 = f2 = 0.0
        for cx in range(2):
            wx = tx if cx else 1.0 - tx
            for cy in range(2):
                wy = ty if cy else 1.0 - ty
                for cz in range(2):
                    wz = tz if cz else 1.0 - tz
                    w = wx * wy * wz
                    if w == 0.0:
                        continue
                    i, j, k = i0 + cx, j0 + cy, k0 + cz
                    p += w * phi[i, j, k]
                    f0 += w * flux[i, j, k, 0]
                    f1 += w * flux[i, j, k, 1]
                    f2 += w * flux[i, j, k, 2]
        e = p / 4.0 - 0.5 * (f0 * normals[m, 0] + f1 * normals[m, 1] + f2 * normals[m, 2])
        out[m] = e if e > 0.0 else 0.0


@njit(cache=True, nogil=True)
def polarized_gain(bq, bu, seen, dop):
    """In place: (q, u) ← (q, u)·(1 + dop·seen/|(q, u)|) where |(q, u)| > 0 (docs/physics.md §10.4; the
    orders ≥ 2 in the orientation of the single wide-angle scattering)."""
    for m in range(bq.size):
        norm = math.hypot(bq[m], bu[m])
        if norm > 0:
            gain = 1.0 + dop * seen[m] / norm
            bq[m] *= gain
            bu[m] *= gain
