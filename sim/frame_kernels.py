"""Compiled (numba) per-pixel passes of whole frames in :mod:`polarstripe.sim.higher`: the P1 irradiance of
the grid's field at the pixels' object points, the orders ≥ 2 added to the backscatter's Stokes, and the
view rays' in-scatter read at each pixel's depth (where it reads kept per scene). Each
replaces numpy arithmetic with the same operations in the same order, one pass instead of several
temporaries (a 640×480 frame is 307 200 pixels: each numpy pass over it costs about a millisecond)."""

from __future__ import annotations

import math

import numpy as np
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
def plane_irradiance(grid, e_field, points, out):
    """out[m] = max(0, E) at ``points`` (m, 3) of a plane, E the trilinear sample of ``e_field`` = φ/4 − F·n/2
    made with the plane's one outward normal n (:func:`field_irradiance`'s value: the sampling is linear;
    one field's eight corners instead of four's)."""
    lo, h, n = grid
    for m in range(points.shape[0]):     # the eight corners written out, zero weights too (a zero term
        i0, tx = _axis(points[m, 0], lo[0], h[0], n[0])      # adds nothing to a finite sum: the same
        j0, ty = _axis(points[m, 1], lo[1], h[1], n[1])      # numbers, without a branch per corner)
        k0, tz = _axis(points[m, 2], lo[2], h[2], n[2])
        sx, sy, sz = 1.0 - tx, 1.0 - ty, 1.0 - tz
        i1, j1, k1 = i0 + 1, j0 + 1, k0 + 1
        e = sx * sy * sz * e_field[i0, j0, k0]
        e += sx * sy * tz * e_field[i0, j0, k1]
        e += sx * ty * sz * e_field[i0, j1, k0]
        e += sx * ty * tz * e_field[i0, j1, k1]
        e += tx * sy * sz * e_field[i1, j0, k0]
        e += tx * sy * tz * e_field[i1, j0, k1]
        e += tx * ty * sz * e_field[i1, j1, k0]
        e += tx * ty * tz * e_field[i1, j1, k1]
        out[m] = e if e > 0.0 else 0.0


@njit(inline="always")
def stokes_norm(q, u):
    """|(q, u)|: √(q² + u²), hypot (slower, safe from underflow) where q² + u² is below 10⁻²⁹⁰."""
    n2 = q * q + u * u
    return math.sqrt(n2) if n2 > 1e-290 else math.hypot(q, u)


@njit(cache=True, nogil=True)
def polarized_gain(bq, bu, seen, dop):
    """In place: (q, u) ← (q, u)·(1 + dop·seen/|(q, u)|) where |(q, u)| > 0 (docs/physics.md §10.4; the
    orders ≥ 2 in the orientation of the single wide-angle scattering)."""
    for m in range(bq.size):
        q, u = bq[m], bu[m]
        norm = stokes_norm(q, u)
        if norm > 0:
            gain = 1.0 + dop * seen[m] / norm
            bq[m] = q * gain
            bu[m] = u * gain


@njit(cache=True, nogil=True)
def view_depths(shape, t0, t1, nk, x_end, index, frac, first=0, end=-1):
    """Where each pixel of a (h, w) image (``shape`` = (h, w, gh, gw)) reads the coarse rays' cumulative
    in-scatter of :func:`~polarstripe.sim.grid_kernels.view_lookup` at its own depth x_end[m], the same for
    every pattern: per neighbour ray q (row r0, r0, r1, r1 and column c0, c1, c0, c1 of the coarse grid)
    index[m, q] = r·(nk + 1) + k, the depth step below the depth, and frac[m, q] the fraction above it; at
    or beyond the ray's end k = nk − 1 and frac 1 (exactly its last value); where the ray adds nothing
    (its weight or length 0, the depth before its start) its first value, 0, with frac 0. Rows [first, end)
    only (end −1: to the last)."""
    h, w, gh, gw = shape
    rows_scale = (gh - 1) / max(h - 1, 1)
    cols_scale = (gw - 1) / max(w - 1, 1)
    for i in range(first, h if end < 0 else end):
        fr = i * rows_scale
        r0 = min(int(fr), max(gh - 2, 0))
        tr = fr - r0
        r1 = min(r0 + 1, gh - 1)
        for j in range(w):
            fc = j * cols_scale
            c0 = min(int(fc), max(gw - 2, 0))
            tc = fc - c0
            c1 = min(c0 + 1, gw - 1)
            m = i * w + j
            x = x_end[m]
            for q in range(4):
                r = (r0 if q < 2 else r1) * gw + (c0 if q % 2 == 0 else c1)
                wq = (tr if q >= 2 else 1 - tr) * (tc if q % 2 == 1 else 1 - tc)
                length = t1[r] - t0[r]
                scale = nk / length if length > 0.0 else 0.0
                u = (x - t0[r]) * scale
                if wq == 0.0 or scale == 0.0 or u <= 0.0:
                    index[m, q], frac[m, q] = r * (nk + 1), 0.0
                elif u >= nk:
                    index[m, q], frac[m, q] = r * (nk + 1) + nk - 1, 1.0
                else:
                    k = int(u)
                    index[m, q], frac[m, q] = r * (nk + 1) + k, u - k


@njit(cache=True, nogil=True)
def view_gather(shape, cum, index, frac, out, first=0, end=-1):
    """out[f, m] = Σ_q w_q·((1 − a)·cum[f, k_q] + a·cum[f, k_q + 1]) with (k_q, a) = (index, frac)[m, q] of
    :func:`view_depths` and w_q the pixel's bilinear weight of neighbour ray q: the operations of
    :func:`~polarstripe.sim.grid_kernels.view_lookup` in its order, so the same numbers. ``cum`` (nf, rays,
    nk + 1); four fields at a time. Rows [first, end) only (end −1: to the last)."""
    h, w, gh, gw = shape
    nf = cum.shape[0]
    flat = cum.shape[1] * cum.shape[2]
    rows_scale = (gh - 1) / max(h - 1, 1)
    cols_scale = (gw - 1) / max(w - 1, 1)
    tcs = np.empty(w)
    for j in range(w):
        fc = j * cols_scale
        tcs[j] = fc - min(int(fc), max(gw - 2, 0))
    for f0 in range(0, nf, 4):
        quad = np.zeros(4 * flat)               # the four fields side by side, flat: entry k at 4k … 4k + 3
        for f in range(f0, min(f0 + 4, nf)):
            one = cum[f].ravel()
            for k in range(flat):
                quad[4 * k + f - f0] = one[k]
        for i in range(first, h if end < 0 else end):
            fr = i * rows_scale
            tr = fr - min(int(fr), max(gh - 2, 0))
            for j in range(w):
                tc = tcs[j]
                m = i * w + j
                a0 = a1 = a2 = a3 = 0.0
                for q in range(4):
                    wq = (1 - tr if q < 2 else tr) * (1 - tc if q % 2 == 0 else tc)
                    k, a = 4 * np.intp(index[m, q]), frac[m, q]
                    b = 1.0 - a
                    a0 += wq * (b * quad[k] + a * quad[k + 4])
                    a1 += wq * (b * quad[k + 1] + a * quad[k + 5])
                    a2 += wq * (b * quad[k + 2] + a * quad[k + 6])
                    a3 += wq * (b * quad[k + 3] + a * quad[k + 7])
                out[f0, m] = a0
                if f0 + 1 < nf:
                    out[f0 + 1, m] = a1
                if f0 + 2 < nf:
                    out[f0 + 2, m] = a2
                if f0 + 3 < nf:
                    out[f0 + 3, m] = a3


@njit(inline="always")
def _half_axis(i, size):
    """Pixel i's coarse coordinate on a twice-coarser axis of ``size`` (i/2 − ¼ clamped to [0, size − 1],
    as cv2.resize's INTER_LINEAR has it): (the lower neighbour, the weight of the upper one)."""
    f = min(max(i / 2.0 - 0.25, 0.0), size - 1.0)
    lo = min(int(f), max(size - 2, 0))
    return lo, f - lo


@njit(cache=True, nogil=True)
def half_up(smooth, p_small, ids_small, ids, albedo, fix, fix_start, a_out, out, first=0, end=-1):
    """A ``preview`` frame's half-resolution parts at twice the resolution, one pass: out[k − 1] (h·w flat)
    the bilinear upsampling of ``smooth[k]`` (hs, ws), k ≥ 1 (cv2.resize INTER_LINEAR's, every pixel), and
    A = ρ·P↑ + H↑ with H = smooth[0] and P↑ the upsampling of ``p_small`` within each object: each pixel
    weighs only the coarse neighbours that see its own object (``ids``, flat), the nearest of them when none
    do, H↑ alone where it sees none. Separable: each output row blends its two coarse rows, then each pair of
    output pixels its two coarse columns (weights ¼, ¾: the bilinear's, equal to it to rounding); A is
    ρ·P↑ + H↑ everywhere (ρ = 0 off the objects), then made again at ``fix`` (:func:`half_fix`, rows
    ``fix_start``), the pixels by an object's edge. Rows [first, end) only (end −1: to the last)."""
    hs, ws = p_small.shape
    w = 2 * ws
    nf = len(smooth)
    rows = np.empty((nf + 1, ws))       # this output row's vertical blends: H, the fields, P
    for i in range(first, 2 * hs if end < 0 else end):
        y0, ty = _half_axis(i, hs)
        y1 = min(y0 + 1, hs - 1)
        m0 = i * w
        for f in range(nf + 1):
            s = p_small if f == nf else smooth[f]
            for x in range(ws):
                rows[f, x] = (1.0 - ty) * s[y0, x] + ty * s[y1, x]
        # pixel 0 reads column 0, 2x + 1 and 2x + 2 columns x, x + 1, w − 1 the last
        for f in range(1, nf):
            o = out[f - 1]
            o[m0] = rows[f, 0]
            for x in range(ws - 1):
                r0, r1 = rows[f, x], rows[f, x + 1]
                o[m0 + 2 * x + 1] = 0.75 * r0 + 0.25 * r1
                o[m0 + 2 * x + 2] = 0.25 * r0 + 0.75 * r1
            o[m0 + w - 1] = rows[f, ws - 1]
        a_out[m0] = albedo[m0] * rows[nf, 0] + rows[0, 0]
        for x in range(ws - 1):
            p0, p1, h0, h1 = rows[nf, x], rows[nf, x + 1], rows[0, x], rows[0, x + 1]
            m = m0 + 2 * x + 1
            a_out[m] = albedo[m] * (0.75 * p0 + 0.25 * p1) + (0.75 * h0 + 0.25 * h1)
            a_out[m + 1] = albedo[m + 1] * (0.25 * p0 + 0.75 * p1) + (0.25 * h0 + 0.75 * h1)
        a_out[m0 + w - 1] = albedo[m0 + w - 1] * rows[nf, ws - 1] + rows[0, ws - 1]
        for e in range(fix_start[i], fix_start[i + 1]):
            m = fix[e]
            j = m - m0
            x0, tx = _half_axis(j, ws)
            x1 = min(x0 + 1, ws - 1)
            hv = (1.0 - tx) * rows[0, x0] + tx * rows[0, x1]
            k = ids[m]
            if k < 0:
                a_out[m] = hv
                continue
            w00, w01, w10, w11 = (1.0 - ty) * (1.0 - tx), (1.0 - ty) * tx, ty * (1.0 - tx), ty * tx
            p = _within(p_small, ids_small, k, y0, y1, x0, x1, w00, w01, w10, w11,
                        min(max(i / 2.0 - 0.25, 0.0), hs - 1.0), min(max(j / 2.0 - 0.25, 0.0), ws - 1.0))
            a_out[m] = albedo[m] * p + hv


def half_fix(ids: np.ndarray, ids_small: np.ndarray, albedo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pixels :func:`half_up` makes A at one by one, the same for every pattern: those of an object
    whose four coarse neighbours do not all see it, and any beside the objects with an albedo (none, as
    the scene's surfaces have it). (flat indices, sorted; the index of each row's first of them, h + 1)."""
    h, w = ids.shape
    hs, ws = ids_small.shape

    def neighbours(n, size):
        lo = np.minimum(np.clip(np.arange(n) / 2.0 - 0.25, 0.0, size - 1.0).astype(np.int64),
                        max(size - 2, 0))
        return lo, np.minimum(lo + 1, size - 1)

    (y0, y1), (x0, x1) = neighbours(h, hs), neighbours(w, ws)
    same = np.ones((h, w), bool)
    for yy in (y0, y1):
        for xx in (x0, x1):
            same &= ids_small[yy[:, None], xx[None, :]] == ids
    fix = np.flatnonzero(((ids >= 0) & ~same) | ((ids < 0) & (albedo.reshape(h, w) != 0)))
    return fix, np.searchsorted(fix, np.arange(h + 1) * w)


@njit(nogil=True)
def _within(small, ids_small, k, y0, y1, x0, x1, w00, w01, w10, w11, fy, fx):
    """:func:`half_up`'s P at a pixel of object k by an edge of it (a call of its own): the bilinear
    weights of the neighbours that see k, renormalised; else the nearest coarse pixel of k within two."""
    acc = wsum = 0.0
    for yy, xx, wq in ((y0, x0, w00), (y0, x1, w01), (y1, x0, w10), (y1, x1, w11)):
        if ids_small[yy, xx] == k:
            acc += wq * small[yy, xx]
            wsum += wq
    if wsum > 1e-9:
        return acc / wsum
    best, val = 1e30, 0.0
    hs, ws = small.shape
    for yy in range(max(int(fy) - 1, 0), min(int(fy) + 3, hs)):
        for xx in range(max(int(fx) - 1, 0), min(int(fx) + 3, ws)):
            if ids_small[yy, xx] == k:
                d = (yy - fy) ** 2 + (xx - fx) ** 2
                if d < best:
                    best, val = d, small[yy, xx]
    return val
