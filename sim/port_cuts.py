"""Where a ray through the water is lit through the projector's port (docs/physics.md §11), compiled (numba):
the light reaching a point (:func:`light_at`: the air ray of :func:`polarstripe.sim.port.through_port` and
its pattern pixel) and the points along a ray where the lit state changes (:func:`lit_cuts`).

The pattern is a ``PatternTable`` record (:mod:`polarstripe.sim.port_kernels`): its lit state can change
only on the lines of its cells (a Gray bit's and its XOR base's columns, a checker's squares) and at the
frame's edges. A ray's piece is split until at most one such line lies between its ends' pattern
coordinates; where the ends differ in lit state the crossing of that line is solved for by regula falsi on
the pattern coordinate, which is nearly linear along a ray (the image of a water ray is a straight line for
a bare pinhole, and nearly one through a port).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from polarstripe.sim.port import through_port


@njit(cache=True, nogil=True)
def light_at(src, pat, px, py, pz, buf):
    """Fill ``buf`` (12,) as :func:`through_port` for the water point (px, py, pz) and return (lit, col, row,
    valid): valid False where no light of the pattern's pinhole reaches the point; buf[9] is J·T."""
    if src.has_port:
        if not through_port(px, py, pz, src.apex, src.normal, src.d, src.t, src.n_a, src.n_g, src.n_w,
                            src.fresnel, buf):
            return False, 0.0, 0.0, False
        buf[9] *= buf[10]
    else:
        vx, vy, vz = px - src.apex[0], py - src.apex[1], pz - src.apex[2]
        d2 = vx * vx + vy * vy + vz * vz
        dist = max(math.sqrt(d2), 1e-300)
        buf[0], buf[1], buf[2] = vx / dist, vy / dist, vz / dist
        buf[3], buf[4], buf[5] = src.apex[0], src.apex[1], src.apex[2]
        buf[6], buf[7], buf[8] = buf[0], buf[1], buf[2]
        buf[9] = 1.0 / max(d2 + src.radius * src.radius, 1e-300)
        buf[10] = 1.0
    if not pat.has_frame:
        return True, 0.0, 0.0, True
    depth = buf[0] * pat.f[0] + buf[1] * pat.f[1] + buf[2] * pat.f[2]
    if depth <= 0.0:
        return False, 0.0, 0.0, False
    col = pat.w / 2.0 + (buf[0] * pat.r[0] + buf[1] * pat.r[1] + buf[2] * pat.r[2]) / depth / pat.s
    row = pat.h / 2.0 - (buf[0] * pat.u[0] + buf[1] * pat.u[1] + buf[2] * pat.u[2]) / depth / pat.s
    lit = 0.0 <= col < pat.w and 0.0 <= row < pat.h and pat.table[int(row), int(col)]
    return lit, col, row, True


@njit(cache=True, nogil=True)
def ray_state(src, pat, ox, oy, oz, dx, dy, dz, x, buf):
    """:func:`light_at` of the point at x on the ray o + x·d."""
    return light_at(src, pat, ox + x * dx, oy + x * dy, oz + x * dz, buf)


@njit(cache=True, nogil=True)
def _outside(pat, ca, ra, cb, rb):
    """Both ends on one outer side of the lit pixels' box: the segment between them lights nothing."""
    return (ca < pat.box[0] and cb < pat.box[0]) or (ca >= pat.box[1] and cb >= pat.box[1]) or \
        (ra < pat.box[2] and rb < pat.box[2]) or (ra >= pat.box[3] and rb >= pat.box[3])


@njit(cache=True, nogil=True)
def _on_grid(v, off, size):
    """Whether the value v is a cell boundary off + k·size (none for an infinite size)."""
    k = (v - off) / size
    return math.isfinite(size) and k == math.floor(k)


@njit(cache=True, nogil=True)
def _boundaries(pat, ca, ra, cb, rb):
    """How many cell boundaries and edges of the pattern lie between two pattern coordinates (an edge on a
    cell boundary counted once)."""
    c0, cs, r0, rs = pat.cells[0], pat.cells[1], pat.cells[2], pat.cells[3]
    n = abs(math.floor((cb - c0) / cs) - math.floor((ca - c0) / cs)) + \
        abs(math.floor((rb - r0) / rs) - math.floor((ra - r0) / rs))
    if not _on_grid(0.0, c0, cs):
        n += (ca < 0.0) != (cb < 0.0)
    if not _on_grid(float(pat.w), c0, cs):
        n += (ca >= pat.w) != (cb >= pat.w)
    if not _on_grid(0.0, r0, rs):
        n += (ra < 0.0) != (rb < 0.0)
    if not _on_grid(float(pat.h), r0, rs):
        n += (ra >= pat.h) != (rb >= pat.h)
    return n


@njit(cache=True, nogil=True)
def _crossing(pat, ca, ra, cb, rb):
    """The one pattern line between two pattern coordinates where the lit state can change: (axis 0 col,
    1 row, its value), or (-1, 0) where there is none or more than one (a corner)."""
    axis, value, found = -1, 0.0, 0
    if pat.convex:                  # the lit set is the box: its four edges
        for k in range(4):
            a, b = (ca, cb) if k < 2 else (ra, rb)
            if (a < pat.box[k]) != (b < pat.box[k]):
                axis, value, found = k // 2, pat.box[k], found + 1
        return (axis, value) if found == 1 else (-1, 0.0)
    for k in range(2):
        a, b = (ca, cb) if k == 0 else (ra, rb)
        off, size = pat.cells[2 * k], pat.cells[2 * k + 1]
        end = float(pat.w if k == 0 else pat.h)
        fa, fb = math.floor((a - off) / size), math.floor((b - off) / size)
        if fa != fb:
            axis, value, found = k, off + size * max(fa, fb), found + 1
        for v in (0.0, end):
            if (a < v) != (b < v) and not (fa != fb and v == off + size * max(fa, fb)):
                axis, value, found = k, v, found + 1
    return (axis, value) if found == 1 else (-1, 0.0)


@njit(cache=True, nogil=True)
def _solve_crossing(src, pat, ox, oy, oz, dx, dy, dz, a, b, fa, fb, axis, value, buf):
    """x in (a, b) where the pattern coordinate ``axis`` of the ray's point equals ``value`` (fa, fb: that
    coordinate minus ``value`` at a and b, of opposite signs): the Illinois variant of regula falsi (the
    coordinate is nearly linear along the ray); NaN where a point on the way gets no light."""
    side = 0
    tol = 1e-12 * (abs(a) + abs(b)) + 1e-15
    for _ in range(60):
        x = (a * fb - b * fa) / (fb - fa)
        if not a < x < b:
            x = 0.5 * (a + b)
        _, c, r, valid = ray_state(src, pat, ox, oy, oz, dx, dy, dz, x, buf)
        if not valid:
            return math.nan
        f = (c if axis == 0 else r) - value
        if (f < 0.0) == (fa < 0.0):
            a, fa = x, f
            if side == -1:
                fb *= 0.5
            side = -1
        else:
            b, fb = x, f
            if side == 1:
                fa *= 0.5
            side = 1
        if b - a <= tol or f == 0.0:
            return x
    return 0.5 * (a + b)


@njit(cache=True, nogil=True)
def _cut(src, pat, ox, oy, oz, dx, dy, dz, a, b, la, ca, ra, va, cb, rb, vb, buf):
    """Where the lit state changes in (a, b), its ends' states differing: the crossing of the one pattern
    line between them (:func:`_crossing`), else 30 bisections."""
    axis, value = _crossing(pat, ca, ra, cb, rb) if va and vb else (-1, 0.0)
    if axis >= 0:
        x = _solve_crossing(src, pat, ox, oy, oz, dx, dy, dz, a, b, (ca if axis == 0 else ra) - value,
                            (cb if axis == 0 else rb) - value, axis, value, buf)
        if x == x:
            return x
    for _ in range(30):
        mid = 0.5 * (a + b)
        if ray_state(src, pat, ox, oy, oz, dx, dy, dz, mid, buf)[0] == la:
            a = mid
        else:
            b = mid
    return 0.5 * (a + b)


@njit(cache=True, nogil=True)
def lit_cuts(src, pat, ox, oy, oz, dx, dy, dz, x0, x1, cuts, buf):
    """Points in (x0, x1) where the lit state changes, in order, into ``cuts``; returns their count.

    A piece is split while more than one cell boundary or edge of the pattern lies between its ends' pattern
    coordinates, except where both ends lie on one outer side of the lit pixels' box; for a convex lit set
    (flood, a stripe) a piece lit at both ends is lit throughout, one unlit at both ends is split while its
    ends' coordinates differ by more than half a pixel. A piece whose ends differ is cut by :func:`_cut`.
    (The image of a water ray is a straight line for a bare pinhole, and nearly one through a port.)"""
    n_cut = 0
    top = 0
    stack_a = np.empty(64)
    stack_b = np.empty(64)
    stack_l = np.empty(64, np.int64)
    st_lit = np.empty(64, np.bool_)          # the state at each piece's end b (each point's state once)
    st_col = np.empty(64)
    st_row = np.empty(64)
    st_ok = np.empty(64, np.bool_)
    first = 4
    for k in range(first - 1, -1, -1):
        stack_a[top] = x0 + (x1 - x0) * k / first
        stack_b[top] = x0 + (x1 - x0) * (k + 1) / first
        stack_l[top] = 0
        st_lit[top], st_col[top], st_row[top], st_ok[top] = ray_state(src, pat, ox, oy, oz, dx, dy, dz,
                                                                   stack_b[top], buf)
        top += 1
    # the pieces come off the stack in order along the ray: a piece's start is the last one's end
    la, ca, ra, va = ray_state(src, pat, ox, oy, oz, dx, dy, dz, x0, buf)
    while top > 0:
        top -= 1
        a, b, lev = stack_a[top], stack_b[top], stack_l[top]
        lb, cb, rb, vb = st_lit[top], st_col[top], st_row[top], st_ok[top]
        if va and vb:
            spread = abs(cb - ca) + abs(rb - ra)
            if _outside(pat, ca, ra, cb, rb) or (pat.convex and la and lb):
                far = False
            elif pat.convex:
                far = not la and not lb and spread > 0.5
            else:
                far = _boundaries(pat, ca, ra, cb, rb) > 1
        else:
            far = va != vb
        if far and lev < 24 and top < 62 and b - a > 1e-9:
            mid = 0.5 * (a + b)
            stack_a[top], stack_b[top], stack_l[top] = mid, b, lev + 1
            top += 1
            stack_a[top], stack_b[top], stack_l[top] = a, mid, lev + 1
            st_lit[top], st_col[top], st_row[top], st_ok[top] = ray_state(src, pat, ox, oy, oz, dx, dy, dz,
                                                                       mid, buf)
            top += 1
            continue
        if la != lb and n_cut < cuts.size:
            cuts[n_cut] = _cut(src, pat, ox, oy, oz, dx, dy, dz, a, b, la, ca, ra, va, cb, rb, vb, buf)
            n_cut += 1
        la, ca, ra, va = lb, cb, rb, vb      # the next piece starts here
    return n_cut
