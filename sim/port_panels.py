"""Single scattering along water rays lit through the projector's port by a finely divided pattern (a Gray
code's bits, a checker), compiled (numba): the integrand interpolated on panels, not a quadrature rule on
every lit piece (docs/physics.md §11).

A ray's part beyond the port's outer face is cut into panels as :func:`~polarstripe.sim.port_kernels.
ray_by_pieces` cuts a lit piece (one per half optical depth and per 0.15 rad of the scattering angle's
change). On each panel the integrand of B and of its camera-frame q, u, v
(:func:`~polarstripe.sim.port_kernels.node_stokes`) and the pattern coordinates (col, row) are taken at
the M = 9 Chebyshev–Lobatto points and interpolated by the polynomial through them (its coefficients in
the panel's coordinate t ∈ [−1, 1]). The lines of the pattern's cells and its frame's edges crossed between
two neighbouring points are solved for on the coordinates' polynomials (Newton from the chord), the lit
state of each piece between crossings read from the pattern's table at its middle, and each run of lit
pieces integrated exactly on the integrands' polynomials (their antiderivatives). A ray costs its panels'
8 points each, whatever the number of its lit pieces (a Gray bit of one-pixel stripes lights hundreds,
each of which cost the piecewise rule 7 points or more); the result differs from the piecewise rule's by
the interpolation's error (~1e−6 of the peak at `preview`). Where a panel's integrand varies by more than
:data:`_SMOOTH` (the light's rise along a ray near the wall, the source's forward lobe) the ray's panels are
halved, up to 3 times; a ray where it still does (a port whose face holds the pinhole, where J peaks) or
where a point gets no light (behind the projector) takes the piecewise rule.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from polarstripe.sim.port_cuts import light_at
from polarstripe.sim.port_kernels import beyond_port, needs_state, node_stokes, ray_by_pieces

M = 9
_T = -np.cos(np.pi * np.arange(M) / (M - 1))               # Chebyshev–Lobatto points on [-1, 1], ascending
_SMOOTH = 4.0      # a panel's largest integrand at most this times its least, else the piecewise rule
_VINV = np.linalg.inv(np.vander(_T, M, increasing=True))   # point values -> coefficients of t^m


@njit(cache=True, nogil=True)
def _horner(a, k, t):
    """Σ_m a[k, m]·t^m."""
    v = 0.0
    for m in range(a.shape[1] - 1, -1, -1):
        v = v * t + a[k, m]
    return v


@njit(cache=True, nogil=True)
def _root(a, k, value, lo, hi, flo, fhi):
    """t in [lo, hi] where the polynomial a[k] equals ``value`` (flo, fhi: its excess at the ends, of
    opposite signs): Newton from the chord's crossing, kept inside the bracket."""
    t = (lo * fhi - hi * flo) / (fhi - flo)
    for _ in range(40):
        g, dg = 0.0, 0.0
        for m in range(M - 1, -1, -1):
            dg = dg * t + g
            g = g * t + a[k, m]
        g -= value
        if g == 0.0:
            return t
        if (g < 0.0) == (flo < 0.0):
            lo = t
        else:
            hi = t
        step = g / dg if dg != 0.0 else math.inf
        new = t - step
        if not lo <= new <= hi:
            new = 0.5 * (lo + hi)
        if abs(new - t) <= 1e-12:
            return new
        t = new
    return t


@njit(cache=True, nogil=True)
def _crossings(a, k, nodes, j, off, size, end, out, n):
    """Append to ``out`` (from n) the t between points j and j + 1 where the coordinate polynomial a[k]
    (values ``nodes`` at the points) crosses a line off + i·size or an edge (0, ``end``) of the frame; returns
    the new count."""
    fa, fb = nodes[j], nodes[j + 1]
    lo_v, hi_v = min(fa, fb), max(fa, fb)
    if hi_v < 0.0 or lo_v > end or lo_v == hi_v:
        return n
    ta, tb = _T[j], _T[j + 1]
    if math.isfinite(size):
        k0 = math.floor((max(lo_v, 0.0) - off) / size) + 1
        k1 = math.floor((min(hi_v, end) - off) / size)
        for i in range(k0, k1 + 1):
            v = off + i * size
            if lo_v < v <= hi_v and 0.0 < v < end and n < out.size:
                out[n] = _root(a, k, v, ta, tb, fa - v, fb - v)
                n += 1
    for v in (0.0, end):
        if lo_v < v <= hi_v and n < out.size:
            out[n] = _root(a, k, v, ta, tb, fa - v, fb - v)
            n += 1
    return n


@njit(cache=True, nogil=True)
def ray_by_panels(src, pat, medium, phase, pol, stateful, ox, oy, oz, dx, dy, dz, x0, lo, hi, cam_r, cam_u,
                  work, buf):
    """(ok, B, q, u, v) of one ray over [lo, hi] (camera-side path from x0; module docstring); ok False
    where a point gets no light, or a panel's integrand still varies more than :data:`_SMOOTH` after the
    panels were halved 3 times (then nothing is summed). ``work`` (4096,) scratch."""
    st = medium[0]
    va = light_at(src, pat, ox + lo * dx, oy + lo * dy, oz + lo * dz, buf)[3]
    mua = -(buf[6] * dx + buf[7] * dy + buf[8] * dz)
    vb = light_at(src, pat, ox + hi * dx, oy + hi * dy, oz + hi * dz, buf)[3]
    mub = -(buf[6] * dx + buf[7] * dy + buf[8] * dz)
    if not (va and vb):
        return False, 0.0, 0.0, 0.0, 0.0
    turn = abs(math.acos(min(max(mua, -1.0), 1.0)) - math.acos(min(max(mub, -1.0), 1.0)))
    n_pan = min(64, 1 + int(st * (hi - lo) / 0.5) + int(turn / 0.15))
    for halving in range(4):
        status, b, q, u, v = _panels(src, pat, medium, phase, pol, stateful, ox, oy, oz, dx, dy, dz, x0, lo,
                                     hi, cam_r, cam_u, n_pan << halving, work, buf)
        if status == 0:
            return True, b, q, u, v
        if status == 2:
            break
    return False, 0.0, 0.0, 0.0, 0.0


@njit(cache=True, nogil=True)
def _panels(src, pat, medium, phase, pol, stateful, ox, oy, oz, dx, dy, dz, x0, lo, hi, cam_r, cam_u, n_pan,
            work, buf):
    """(status, B, q, u, v) of the ray on ``n_pan`` panels: status 0 done, 1 a panel's integrand varies
    more than :data:`_SMOOTH`, 2 a point gets no light."""
    vals = np.empty((6, M))          # B, q, u, v, col, row at the points
    coef = np.empty((6, M))          # their polynomials' coefficients in the panel's t
    prim = np.zeros((4, M + 1))      # those of the integrands' integrals from t = 0
    acc = np.zeros(4)
    w, h = float(pat.w), float(pat.h)
    for p in range(n_pan):
        pa = lo + (hi - lo) * p / n_pan
        pb = lo + (hi - lo) * (p + 1) / n_pan
        half, mid = 0.5 * (pb - pa), 0.5 * (pb + pa)
        for j in range(M):
            if j == 0 and p > 0:                 # the last panel's end
                for k in range(6):
                    vals[k, 0] = vals[k, M - 1]
                continue
            _, col, row, valid, fb, fq, fu, fv = node_stokes(src, pat, phase, pol, medium, stateful, ox, oy,
                                                             oz, dx, dy, dz, mid + half * _T[j], x0, cam_r,
                                                             cam_u, buf)
            if not valid:
                return 2, 0.0, 0.0, 0.0, 0.0
            vals[0, j], vals[1, j], vals[2, j], vals[3, j], vals[4, j], vals[5, j] = fb, fq, fu, fv, col, row
        lo_b, hi_b = vals[0].min(), vals[0].max()
        if not lo_b * _SMOOTH >= hi_b:            # a peak (the source's forward lobe, a port at the pinhole)
            return 1, 0.0, 0.0, 0.0, 0.0
        for k in range(6):                       # the polynomials' coefficients, the integrands' integrals'
            for m in range(M):
                v = 0.0
                for j in range(M):
                    v += _VINV[m, j] * vals[k, j]
                coef[k, m] = v
                if k < 4:
                    prim[k, m + 1] = v / (m + 1)
        n = 0
        for j in range(M - 1):
            n = _crossings(coef, 4, vals[4], j, pat.cells[0], pat.cells[1], w, work, n)
            n = _crossings(coef, 5, vals[5], j, pat.cells[2], pat.cells[3], h, work, n)
        cuts = np.sort(work[:n])
        run = -2.0                               # the start of the current run of lit pieces (< -1: none)
        for q in range(n + 1):
            ta = -1.0 if q == 0 else cuts[q - 1]
            tb = 1.0 if q == n else cuts[q]
            lit = False
            if tb > ta:
                tm = 0.5 * (ta + tb)
                col, row = _horner(coef, 4, tm), _horner(coef, 5, tm)
                lit = 0.0 <= col < w and 0.0 <= row < h and pat.table[int(row), int(col)]
            if lit and run < -1.0:
                run = ta
            if run >= -1.0 and (not lit or q == n):
                end = tb if lit else ta
                for k in range(4):
                    acc[k] += half * (_horner(prim, k, end) - _horner(prim, k, run))
                run = -2.0
    return 0, acc[0], acc[1], acc[2], acc[3]


@njit(cache=True, nogil=True)
def port_line_integrals(panels, src, pat, medium, phase, pol, origin, dirs, x0s, x1s, cam_r, cam_u, gl_t,
                        gl_w, out):
    """B and its camera-frame Stokes (q, u, v) of each ray into ``out`` (a ``Stokes`` record, each (n,)),
    over its part beyond the projector port's face: by :func:`ray_by_panels` with ``panels`` (the piecewise
    rule where that gives up), else by :func:`~polarstripe.sim.port_kernels.ray_by_pieces`; ``origin``
    (1, 3) or (n, 3), ``cam_r``/``cam_u`` (1, 3) or (n, 3)."""
    b_out, q_out, u_out, v_out = out
    buf = np.zeros(12)
    work = np.empty(4096)
    stateful = needs_state(src, pol)
    per_o = origin.shape[0] > 1
    per_c = cam_r.shape[0] > 1
    for i in range(dirs.shape[0]):
        x0, x1 = x0s[i], x1s[i]
        b_out[i] = 0.0
        if pol.on:
            q_out[i] = u_out[i] = v_out[i] = 0.0
        if not x1 > x0:
            continue
        ko = i if per_o else 0
        kc = i if per_c else 0
        ox, oy, oz = origin[ko, 0], origin[ko, 1], origin[ko, 2]
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        lo, hi = beyond_port(src, ox, oy, oz, dx, dy, dz, x0, x1)
        if not hi > lo:
            continue
        ok, b, q, u, v = 0, 0.0, 0.0, 0.0, 0.0
        if panels:
            ok, b, q, u, v = ray_by_panels(src, pat, medium, phase, pol, stateful, ox, oy, oz, dx, dy, dz, x0,
                                           lo, hi, cam_r[kc], cam_u[kc], work, buf)
        if not ok:
            b, q, u, v = ray_by_pieces(src, pat, medium, phase, pol, stateful, ox, oy, oz, dx, dy, dz, x0, lo,
                                       hi, cam_r[kc], cam_u[kc], gl_t, gl_w, work, buf)
        b_out[i] = b
        if pol.on:
            q_out[i], u_out[i], v_out[i] = q, u, v
