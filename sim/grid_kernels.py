"""Compiled (numba) loops of the higher-order grid (:mod:`polarstripe.sim.multiple`): beams deposited into the
cells, trilinear sampling of the fields, and the in-scattered radiance integrated along view rays.

The grid is cell-centred over the medium box: cell (i, j, k) has centre lo + (i + ½, j + ½, k + ½)·h. A field
is a fluence φ (nx, ny, nz) [W/m²] with its flux vector F (nx, ny, nz, 3) [W/m²] (first angular moment,
F = ∫ L ω dω). Trilinear weights are taken between cell centres, clamped at the outermost centres.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from polarstripe.sim.kernels import phase_value, segment_in_box


class GridArgs(NamedTuple):
    """The cell grid: box corner ``lo`` (3,), cell size ``h`` (3,) [m] and cell counts ``n`` (3,) int64."""

    lo: np.ndarray
    h: np.ndarray
    n: np.ndarray


class Beams(NamedTuple):
    """Straight beams: origins (m, 3) (or (1, 3) shared), unit directions (m, 3), the power per unit length
    they start with [W/m] (m,), where they start and end along the beam (m,) [m] and the distance already
    travelled in the medium at the start (m,) [m]."""

    origin: np.ndarray
    dirs: np.ndarray
    power: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    pre: np.ndarray


@njit(cache=True, nogil=True)
def _axis(p, lo, h, n):
    """Lower cell index and trilinear fraction of coordinate p on one axis (clamped to the centres)."""
    if n < 2:
        return 0, 0.0
    f = (p - lo) / h - 0.5
    if f < 0.0:
        f = 0.0
    elif f > n - 1:
        f = float(n - 1)
    i = int(math.floor(f))
    if i > n - 2:
        i = n - 2
    return i, f - i


@njit(cache=True, nogil=True)
def deposit_beams(grid, beams, sigma, step, phi, flux):
    """Add the fluence and flux of ``beams`` into the cells: a beam carrying p [W/m] at distance s from its
    start deposits p·e^{−σ s} ds along its way (exact per step), spread trilinearly from the step's middle;
    ``phi`` and ``flux`` receive Σ p∫e^{−σs}ds / V and the same times the direction (V the cell volume)."""
    lo, h, n = grid
    vol = h[0] * h[1] * h[2]
    origin, dirs, power, t0, t1, pre = beams
    per = origin.shape[0] > 1
    for b in range(dirs.shape[0]):
        if not t1[b] > t0[b] or power[b] <= 0.0:
            continue
        ko = b if per else 0
        ox, oy, oz = origin[ko, 0], origin[ko, 1], origin[ko, 2]
        dx, dy, dz = dirs[b, 0], dirs[b, 1], dirs[b, 2]
        length = t1[b] - t0[b]
        ns = max(1, int(math.ceil(length / step)))
        ds = length / ns
        for s in range(ns):
            a0 = pre[b] + s * ds
            if sigma > 0.0:
                w = (math.exp(-sigma * a0) - math.exp(-sigma * (a0 + ds))) / sigma
                if sigma * a0 > 700.0:
                    break
            else:
                w = ds
            w *= power[b] / vol
            t = t0[b] + (s + 0.5) * ds
            i0, tx = _axis(ox + t * dx, lo[0], h[0], n[0])
            j0, ty = _axis(oy + t * dy, lo[1], h[1], n[1])
            k0, tz = _axis(oz + t * dz, lo[2], h[2], n[2])
            for cx in range(2):
                wx = tx if cx else 1.0 - tx
                if wx == 0.0:
                    continue
                for cy in range(2):
                    wy = ty if cy else 1.0 - ty
                    if wy == 0.0:
                        continue
                    for cz in range(2):
                        wz = tz if cz else 1.0 - tz
                        if wz == 0.0:
                            continue
                        i, j, k = i0 + cx, j0 + cy, k0 + cz
                        ww = w * wx * wy * wz
                        phi[i, j, k] += ww
                        flux[i, j, k, 0] += ww * dx
                        flux[i, j, k, 1] += ww * dy
                        flux[i, j, k, 2] += ww * dz


@njit(cache=True, nogil=True)
def sample_fields(grid, phi, flux, points, phi_out, flux_out):
    """Trilinear φ and F at ``points`` (m, 3) into ``phi_out`` (m,) and ``flux_out`` (m, 3)."""
    lo, h, n = grid
    for m in range(points.shape[0]):
        i0, tx = _axis(points[m, 0], lo[0], h[0], n[0])
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
        phi_out[m] = p
        flux_out[m, 0], flux_out[m, 1], flux_out[m, 2] = f0, f1, f2


class ViewArgs(NamedTuple):
    """Emissions J_i(Y, ω) = c_i·(φ_i + 3 g_i F_i·ω) [W m⁻³ sr⁻¹] (clamped at 0) of the fields i (arrays c, g
    (k,)) seen along rays from ``origin`` ((1, 3) shared, or (m, 3) one per ray: a camera behind a port) with
    the view attenuations σ_i (array (k,))."""

    c: np.ndarray
    g: np.ndarray
    sigma: np.ndarray
    origin: np.ndarray


@njit(cache=True, nogil=True)
def view_cumulative(grid, phi, flux, view, dirs, t0, t1, cum):
    """cum[i, r, j] = ∫_{t0}^{t0 + j·Δ} J_i(C + x·d, −d) e^{−σ_i(x − t0)} dx, Δ = (t1 − t0)/(K − 1) with
    K = cum.shape[2], for the fields phi (k, nx, ny, nz), flux (k, nx, ny, nz, 3): the in-scattered radiance
    of ray r up to each of K evenly spaced depths (J at each step's middle, the exponential exact per
    step)."""
    lo, h, n = grid
    c, g, sigma, origin = view
    nf = phi.shape[0]
    nk = cum.shape[2] - 1
    per = origin.shape[0] > 1
    step_w, decay = np.empty(nf), np.empty(nf)     # a step's weight at the ray's start, its decay a step
    for r in range(dirs.shape[0]):
        ko = r if per else 0
        for i in range(nf):
            cum[i, r, 0] = 0.0
        length = t1[r] - t0[r]
        if not length > 0.0:
            for i in range(nf):
                for j in range(nk):
                    cum[i, r, j + 1] = 0.0
            continue
        ds = length / nk
        for f in range(nf):      # ∫ e^{−σa} over step j = e^{−σjΔ}·(1 − e^{−σΔ})/σ: one exp a ray
            sf = sigma[f]
            step_w[f] = -math.expm1(-sf * ds) / sf if sf > 0.0 else ds
            decay[f] = math.exp(-sf * ds) if sf > 0.0 else 1.0
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        for j in range(nk):
            a0 = j * ds
            x = t0[r] + a0 + 0.5 * ds
            i0, tx = _axis(origin[ko, 0] + x * dx, lo[0], h[0], n[0])
            j0, ty = _axis(origin[ko, 1] + x * dy, lo[1], h[1], n[1])
            k0, tz = _axis(origin[ko, 2] + x * dz, lo[2], h[2], n[2])
            for f in range(nf):  # sample_fields' trilinear loop, written out: a shared helper taking the
                p = 0.0            # field's slices cost 9 % of a preview frame (measured)
                fd = 0.0
                w = step_w[f]
                step_w[f] = w * decay[f]
                for cx in range(2):
                    wx = tx if cx else 1.0 - tx
                    for cy in range(2):
                        wy = ty if cy else 1.0 - ty
                        for cz in range(2):
                            wz = tz if cz else 1.0 - tz
                            ww = wx * wy * wz
                            if ww == 0.0:
                                continue
                            a, b, e = i0 + cx, j0 + cy, k0 + cz
                            p += ww * phi[f, a, b, e]
                            fd += ww * (flux[f, a, b, e, 0] * dx + flux[f, a, b, e, 1] * dy
                                        + flux[f, a, b, e, 2] * dz)
                jv = c[f] * (p - 3.0 * g[f] * fd)
                cum[f, r, j + 1] = cum[f, r, j] + max(jv, 0.0) * w


@njit(cache=True, nogil=True)
def view_lookup(shape, t0, t1, cum, x_end, out, rows=(0, -1)):
    """Per pixel of a (h, w) image (``shape`` = (h, w, gh, gw)): out[f, m] the coarse rays' cumulative
    in-scatter of field f at the pixel's own depth x_end[m], bilinear between the four coarse rays around it
    (coarse ray (a, b) sits at pixel row a·(h − 1)/(gh − 1), column b·(w − 1)/(gw − 1)); on each coarse ray
    linear between its evenly spaced depths, clamped to its ends. ``rows`` = (first, end) limits the work to
    those image rows (end −1: to the last; each pixel is computed on its own, so bands are bit-identical to
    the whole)."""
    h, w, gh, gw = shape
    nf = cum.shape[0]
    nk = cum.shape[2] - 1
    rows_scale = (gh - 1) / max(h - 1, 1)
    cols_scale = (gw - 1) / max(w - 1, 1)
    scale = np.empty(t0.size)
    for r in range(t0.size):
        length = t1[r] - t0[r]
        scale[r] = nk / length if length > 0.0 else 0.0
    col0 = np.empty(w, np.int64)
    col1 = np.empty(w, np.int64)
    tcs = np.empty(w)
    for j in range(w):
        fc = j * cols_scale
        c0 = min(int(fc), max(gw - 2, 0))
        col0[j], col1[j], tcs[j] = c0, min(c0 + 1, gw - 1), fc - c0
    rays = np.empty(4, np.int64)
    wts = np.empty(4)
    end = h if rows[1] < 0 else rows[1]
    for i in range(rows[0], end):
        fr = i * rows_scale
        r0 = min(int(fr), max(gh - 2, 0))
        tr = fr - r0
        r1 = min(r0 + 1, gh - 1)
        for j in range(w):
            m = i * w + j
            c0, c1, tc = col0[j], col1[j], tcs[j]
            rays[0], rays[1], rays[2], rays[3] = r0 * gw + c0, r0 * gw + c1, r1 * gw + c0, r1 * gw + c1
            wts[0], wts[1], wts[2], wts[3] = (1 - tr) * (1 - tc), (1 - tr) * tc, tr * (1 - tc), tr * tc
            for f in range(nf):
                out[f, m] = 0.0
            x = x_end[m]
            for q in range(4):
                r = rays[q]
                wq = wts[q]
                if wq == 0.0 or scale[r] == 0.0:
                    continue
                u = (x - t0[r]) * scale[r]
                if u <= 0.0:
                    continue
                if u >= nk:
                    for f in range(nf):
                        out[f, m] += wq * cum[f, r, nk]
                    continue
                k = int(u)
                a = u - k
                for f in range(nf):
                    out[f, m] += wq * ((1.0 - a) * cum[f, r, k] + a * cum[f, r, k + 1])


@njit(cache=True, nogil=True, inline="always")
def unit_toward(eye, x, y, z):
    """The unit vector from (x, y, z) to ``eye`` (0 when they coincide)."""
    ex, ey, ez = eye[0] - x, eye[1] - y, eye[2] - z
    en = math.sqrt(ex * ex + ey * ey + ez * ez)
    if en > 0.0:
        return ex / en, ey / en, ez / en
    return ex, ey, ez


@njit(cache=True, nogil=True, inline="always")
def patch_glow(patches, p, yx, yy, yz, ex, ey, ez, phase, sigma):
    """P̃(μ_p) Ω_p e^{−σ̃ r_p} of patch ``p`` at the point (yx, yy, yz), (ex, ey, ez) the unit direction from
    it to the eye; 0 where the point is on or behind the patch (:func:`glow_emission`)."""
    vx, vy, vz = yx - patches[p, 0], yy - patches[p, 1], yz - patches[p, 2]
    r2 = vx * vx + vy * vy + vz * vz
    r = math.sqrt(r2)
    if r <= 0.0:
        return 0.0
    cos_p = (vx * patches[p, 3] + vy * patches[p, 4] + vz * patches[p, 5]) / r
    if cos_p <= 0.0:
        return 0.0
    area = patches[p, 6]
    omega = area * cos_p / (r2 + area / (2.0 * math.pi))
    mu = (vx * ex + vy * ey + vz * ez) / r
    return phase_value(phase, 1.0 - mu, 1.0 + mu) * omega * math.exp(-sigma * r)


@njit(cache=True, nogil=True)
def glow_emission(points, eye, patches, phase, sigma, sigma_s, out):
    """Once-scattered glow toward ``eye`` at ``points`` (m, 3): out[m] = σ̃_s Σ_p P̃(μ_p) R_p Ω_p e^{−σ̃ r_p}
    [W m⁻³ sr⁻¹], over Lambertian patches (centre, normal, area, radiance R [W sr⁻¹ m⁻²]) packed as
    ``patches`` (k, 8), with the patch's solid angle regularised as Ω = A cos/(r² + A/2π) (a disk of area A
    seen from its centre subtends 2π) and μ_p the cosine between the patch's light, (Y − O)/r, and the
    direction from the point to ``eye``."""
    for m in range(points.shape[0]):
        yx, yy, yz = points[m, 0], points[m, 1], points[m, 2]
        ex, ey, ez = unit_toward(eye, yx, yy, yz)
        acc = 0.0
        for p in range(patches.shape[0]):
            acc += patch_glow(patches, p, yx, yy, yz, ex, ey, ez, phase, sigma) * patches[p, 7]
        out[m] = sigma_s * acc


@njit(cache=True, nogil=True)
def segment_lengths(a, points, lo, hi, out):
    """out[m] = length [m] of the segment a (3,) → points[m] inside the box [lo, hi]."""
    for m in range(points.shape[0]):
        out[m] = segment_in_box(a[0], a[1], a[2], points[m, 0], points[m, 1], points[m, 2], lo, hi)


@njit(cache=True, nogil=True)
def coarse_silhouettes(t_coarse, t_own, width, step, bad, first=0, end=-1):
    """bad[m] marks the pixels of the (h, w) image (flat, ``width`` = w) whose four coarse neighbours of
    :func:`upsample_grid` end their rays (t_coarse (gh, gw)) more than max(1 cm, 1 %) from their own
    (t_own), i.e. silhouettes, to be computed exactly. Pixels [first, end) only (end −1: to the last)."""
    gh, gw = t_coarse.shape
    n = t_own.size if end < 0 else end
    rs = cs = 1.0 / step
    for m in range(first, n):
        fr = (m // width) * rs
        fc = (m % width) * cs
        r0 = min(int(fr), max(gh - 2, 0))
        c0 = min(int(fc), max(gw - 2, 0))
        r1, c1 = min(r0 + 1, gh - 1), min(c0 + 1, gw - 1)
        own = t_own[m]
        tol = max(0.01, 0.01 * abs(own))
        b = False
        for rr, cc in ((r0, c0), (r0, c1), (r1, c0), (r1, c1)):
            d = t_coarse[rr, cc] - own
            if not abs(d) <= tol:
                b = True
        bad[m] = b


@njit(cache=True, nogil=True)
def upsample_grid(coarse, width, step, out, first=0, end=-1):
    """Bilinear upsampling of coarse (k, gh, gw) fields sampled at every ``step``-th pixel row and column
    (row a·step, column b·step) to the (h, w) image (flat, ``width`` = w) into out (k, h·w). Image rows
    [first, end) only (end −1: to the last)."""
    k, gh, gw = coarse.shape
    h = out.shape[1] // width
    rs = cs = 1.0 / step
    col0 = np.empty(width, np.int64)
    tcs = np.empty(width)
    for j in range(width):
        fc = j * cs
        col0[j] = min(int(fc), max(gw - 2, 0))
        tcs[j] = fc - col0[j]
    for i in range(first, h if end < 0 else end):
        fr = i * rs
        r0 = min(int(fr), max(gh - 2, 0))
        tr = fr - r0
        r1 = min(r0 + 1, gh - 1)
        for q in range(k):
            a = coarse[q, r0]
            b = coarse[q, r1]
            o = out[q, i * width:(i + 1) * width]
            for j in range(width):
                c0 = col0[j]
                c1 = min(c0 + 1, gw - 1)
                tc = tcs[j]
                o[j] = ((1 - tr) * ((1 - tc) * a[c0] + tc * a[c1])
                        + tr * ((1 - tc) * b[c0] + tc * b[c1]))
