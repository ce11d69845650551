"""Compiled (numba) single scattering through flat ports (docs/physics.md §11): the eq. 13 line integral along
water rays whose light reaches each point through the projector's port.

Along a ray O + x·d over [x0, x1] (in the medium, before the first object):

    B = ∫ σ_s P(μ) I₀ T J e^{−σ_t (ℓ_L(Y) + x − x0)} (1 + m12/m11·DOP_L·q_in) lit(Y) dx,   μ = w·(−d)

with w, J, T and the exit point E of :func:`polarstripe.sim.port.through_port` (or, without a projector
port, w = (Y − L)/|Y − L|, J·T = 1/(|Y − L|² + r_s²), E = L), ℓ_L(Y) the length of E→Y inside the medium box,
and lit(Y) the pattern pixel of the air ray (a table of the pattern). The source is outside the water, so
the integrand has no 1/d² peak on the ray and is summed by Gauss–Legendre in x. The lit pieces are found by
subdividing the ray until at most one boundary of the pattern lies between the ends of a piece
(:func:`lit_cuts`), then bisecting each piece whose ends differ in lit state. The Stokes sums are the
Rayleigh-δ Mueller model of :func:`polarstripe.sim.kernels.line_integrals`, node by node, rotated into the
camera's axes carried through the camera's port (so q, u come out in the camera frame). Through a projector
port with Fresnel faces the source's Stokes vector at each node is the port's Mueller matrix times the
source's (:func:`polarstripe.sim.port.diattenuate`): its intensity I₀·J·i' instead of I₀·J·T, and a state
changed toward the port's p axis (even an unpolarized source's light is polarized by (T_p − T_s)/(T_p + T_s)).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from polarstripe.sim.kernels import phase_value, segment_in_box
from polarstripe.sim.port import carry_frame, diattenuate, p_axis, through_port, transmittances_sp
from polarstripe.sim.stokes_kernels import source_state


class PortSource(NamedTuple):
    """The light: pinhole ``apex``, port ``normal``, d, t, indices, ``fresnel``, ``has_port`` (False: the
    bare point source, softened by ``radius``), ``intensity`` I₀ [W/sr]."""

    apex: np.ndarray
    normal: np.ndarray
    d: float
    t: float
    n_a: float
    n_g: float
    n_w: float
    fresnel: bool
    has_port: bool
    radius: float
    intensity: float


class PatternTable(NamedTuple):
    """The projector's pinhole (f, r, u, pitch s, w, h), ``has_frame`` (False: a point source, all lit), the
    lit table (h, w) bool, the cells (col offset, col size, row offset, row size) [pattern pixels] whose
    boundaries hold every change of the lit state, the lit pixels' box (col_lo, col_hi, row_lo,
    row_hi) and ``convex`` (the lit set is one rectangle: flood, a stripe)."""

    f: np.ndarray
    r: np.ndarray
    u: np.ndarray
    s: float
    w: int
    h: int
    has_frame: bool
    table: np.ndarray
    cells: np.ndarray
    box: np.ndarray
    convex: bool


class PortPolarization(NamedTuple):
    """Stokes sums on (``on``), the m12 intensity term (``mueller``), the source E-field and fast axis, DOP_L,
    the Rayleigh-δ reduced factors Δ (``big``) and ΔΔ' (``big44``), ``qwp`` (a quarter-wave plate). A
    projector port with Fresnel faces (``PortSource.fresnel``) applies its Mueller matrix to the source."""

    on: bool
    mueller: bool
    e_field: np.ndarray
    fast_axis: np.ndarray
    dop_l: float
    big: float
    big44: float
    qwp: bool


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
def _through_source_port(src, ax, ay, az, wx, wy, wz, ix, iy, iz, jx, jy, jz, val, q, u, v):
    """The source's unit Stokes (1, q, u, v) in the scattering frame (e_par_in = i, e_perp = j) of a node
    lit along air ray a and water ray w, through the projector port's Mueller matrix: (val·i'/T, q'/i',
    u'/i', v'/i'), val carrying the unpolarized T."""
    c = ax * src.normal[0] + ay * src.normal[1] + az * src.normal[2]
    ts, tp = transmittances_sp(src.n_a * math.sqrt(max(1.0 - c * c, 0.0)), src.t, src.n_a, src.n_g, src.n_w,
                               True)
    pax, pay, paz = p_axis(ax, ay, az, src.normal[0], src.normal[1], src.normal[2])
    px, py, pz = carry_frame(pax, pay, paz, ax, ay, az, wx, wy, wz, src.normal[0], src.normal[1],
                             src.normal[2])
    cx, cy = px * ix + py * iy + pz * iz, px * jx + py * jy + pz * jz
    r2 = cx * cx + cy * cy
    c2, s2 = ((cx * cx - cy * cy) / r2, 2.0 * cx * cy / r2) if r2 > 0.0 else (1.0, 0.0)
    i1, q1, u1, v1 = diattenuate(ts, tp, c2, s2, 1.0, q, u, v)
    return val * i1 / (0.5 * (ts + tp)), q1 / i1, u1 / i1, v1 / i1


@njit(cache=True, nogil=True)
def source_port_gain(air, normal, t, n_a, n_g, n_w, e_field, fast_axis, qwp, dop_l, out):
    """i'/T of the source's light through its port along each air ray ``air`` (n, 3) into ``out`` (n,): the
    port's Mueller matrix's intensity 1 + (T_p − T_s)/(T_p + T_s)·Q_p, Q_p the source's Stokes along the p
    axis (the E-field's and fast axis's components on p = s × a and s, docs/physics.md §5.1)."""
    for i in range(air.shape[0]):
        ax, ay, az = air[i, 0], air[i, 1], air[i, 2]
        c = ax * normal[0] + ay * normal[1] + az * normal[2]
        ts, tp = transmittances_sp(n_a * math.sqrt(max(1.0 - c * c, 0.0)), t, n_a, n_g, n_w, True)
        px, py, pz = p_axis(ax, ay, az, normal[0], normal[1], normal[2])
        sx, sy, sz = ay * pz - az * py, az * px - ax * pz, ax * py - ay * px      # s = a × p
        aa = e_field[0] * px + e_field[1] * py + e_field[2] * pz
        bb = e_field[0] * sx + e_field[1] * sy + e_field[2] * sz
        af = fast_axis[0] * px + fast_axis[1] * py + fast_axis[2] * pz
        bf = fast_axis[0] * sx + fast_axis[1] * sy + fast_axis[2] * sz
        q_p = dop_l * source_state(aa, bb, af, bf, qwp)[0]
        out[i] = 1.0 + (tp - ts) / (tp + ts) * q_p


@njit(cache=True, nogil=True)
def _state(src, pat, ox, oy, oz, dx, dy, dz, x, buf):
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
        _, c, r, valid = _state(src, pat, ox, oy, oz, dx, dy, dz, x, buf)
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
def lit_cuts(src, pat, ox, oy, oz, dx, dy, dz, x0, x1, cuts, buf):
    """Points in (x0, x1) where the lit state changes, in order, into ``cuts``; returns their count.

    A piece is split while more than one cell boundary or edge of the pattern lies between its ends' pattern
    coordinates, except where both ends lie on one outer side of the lit pixels' box; for a convex lit set
    (flood, a stripe) a piece lit at both ends is lit throughout, one unlit at both ends is split while its
    ends' coordinates differ by more than half a pixel. A piece whose ends differ is bisected to its cut.
    (The image of a water ray is a straight line for a bare pinhole, and nearly one through a port.)"""
    n_cut = 0
    top = 0
    stack_a = np.empty(64)
    stack_b = np.empty(64)
    stack_l = np.empty(64, np.int64)
    first = 4
    for k in range(first - 1, -1, -1):
        stack_a[top] = x0 + (x1 - x0) * k / first
        stack_b[top] = x0 + (x1 - x0) * (k + 1) / first
        stack_l[top] = 0
        top += 1
    while top > 0:
        top -= 1
        a, b, lev = stack_a[top], stack_b[top], stack_l[top]
        la, ca, ra, va = _state(src, pat, ox, oy, oz, dx, dy, dz, a, buf)
        lb, cb, rb, vb = _state(src, pat, ox, oy, oz, dx, dy, dz, b, buf)
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
            top += 1
            continue
        if la != lb and n_cut < cuts.size:
            axis, value = _crossing(pat, ca, ra, cb, rb) if va and vb else (-1, 0.0)
            if axis >= 0:
                x = _solve_crossing(src, pat, ox, oy, oz, dx, dy, dz, a, b, (ca if axis == 0 else ra) - value,
                                    (cb if axis == 0 else rb) - value, axis, value, buf)
                if x == x:
                    cuts[n_cut] = x
                    n_cut += 1
                    continue
            for _ in range(30):
                mid = 0.5 * (a + b)
                lm = _state(src, pat, ox, oy, oz, dx, dy, dz, mid, buf)[0]
                if lm == la:
                    a = mid
                else:
                    b = mid
            cuts[n_cut] = 0.5 * (a + b)
            n_cut += 1
    return n_cut


@njit(cache=True, nogil=True)
def port_line_integrals(src, pat, medium, phase, pol, origin, dirs, x0s, x1s, cam_r, cam_u, gl_t, gl_w, out):
    """B and its camera-frame Stokes (q, u, v) of each ray (module docstring) into ``out`` (a ``Stokes``
    record, each (n,)); ``origin`` (1, 3) or (n, 3), ``cam_r``/``cam_u`` (1, 3) or (n, 3)."""
    st, ss, box_lo, box_hi = medium
    b_out, q_out, u_out, v_out = out
    buf = np.zeros(12)
    cuts = np.empty(4096)        # a ray crosses at most w + h pattern lines
    depol_big, big44 = pol.big, pol.big44
    ex, ey, ez = pol.e_field[0], pol.e_field[1], pol.e_field[2]
    fx, fy, fz = pol.fast_axis[0], pol.fast_axis[1], pol.fast_axis[2]
    nx, ny, nz = src.normal[0], src.normal[1], src.normal[2]
    dia = src.has_port and src.fresnel             # the projector port's Mueller matrix on the source
    stateful = pol.mueller or pol.on or (dia and pol.dop_l > 0.0)
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
        n_cut = lit_cuts(src, pat, ox, oy, oz, dx, dy, dz, x0, x1, cuts, buf)
        b_ray = q_ray = u_ray = v_ray = 0.0
        for p in range(n_cut + 1):
            a = x0 if p == 0 else cuts[p - 1]
            b = x1 if p == n_cut else cuts[p]
            if not b > a or not _state(src, pat, ox, oy, oz, dx, dy, dz, 0.5 * (a + b), buf)[0]:
                continue
            # sub-pieces: one per half optical depth and per 0.15 rad of the scattering angle's change
            wa = _state(src, pat, ox, oy, oz, dx, dy, dz, a, buf)[3]
            mua = -(buf[6] * dx + buf[7] * dy + buf[8] * dz) if wa else 0.0
            wb = _state(src, pat, ox, oy, oz, dx, dy, dz, b, buf)[3]
            mub = -(buf[6] * dx + buf[7] * dy + buf[8] * dz) if wb else 0.0
            turn = abs(math.acos(min(max(mua, -1.0), 1.0)) - math.acos(min(max(mub, -1.0), 1.0)))
            n_sub = min(64, 1 + int(st * (b - a) / 0.5) + int(turn / 0.15))
            for sp in range(n_sub):
                sa = a + (b - a) * sp / n_sub
                sb = a + (b - a) * (sp + 1) / n_sub
                half, mid = 0.5 * (sb - sa), 0.5 * (sb + sa)
                for k in range(gl_t.size):
                    x = mid + half * gl_t[k]
                    px, py, pz = ox + x * dx, oy + x * dy, oz + x * dz
                    lit, _, _, valid = light_at(src, pat, px, py, pz, buf)
                    if not valid:
                        continue
                    wx, wy, wz = buf[6], buf[7], buf[8]
                    mu = -(wx * dx + wy * dy + wz * dz)
                    omm, opm = 1.0 - mu, 1.0 + mu
                    ell = 0.0
                    if st > 0.0:
                        ell = segment_in_box(buf[3], buf[4], buf[5], px, py, pz, box_lo, box_hi)
                    val = gl_w[k] * half * ss * src.intensity * buf[9] * phase_value(phase, omm, opm) * \
                        math.exp(-st * (ell + x - x0))
                    if not stateful:
                        b_ray += val
                        continue
                    # the scattering plane: e_perp = normalize(w × (−d)), e_par_in = e_perp × w,
                    # e_par_out = e_perp × (−d); the source's E-field carried through its port
                    pxx, pyy, pzz = -(wy * dz - wz * dy), -(wz * dx - wx * dz), -(wx * dy - wy * dx)
                    pn = math.sqrt(pxx * pxx + pyy * pyy + pzz * pzz)
                    if pn < 1e-12:
                        hx, hy, hz = (1.0, 0.0, 0.0) if abs(dx) < 0.9 else (0.0, 1.0, 0.0)
                        pxx, pyy, pzz = dy * hz - dz * hy, dz * hx - dx * hz, dx * hy - dy * hx
                        pn = math.sqrt(pxx * pxx + pyy * pyy + pzz * pzz)
                    pxx, pyy, pzz = pxx / pn, pyy / pn, pzz / pn
                    ix, iy, iz = pyy * wz - pzz * wy, pzz * wx - pxx * wz, pxx * wy - pyy * wx
                    ax_, ay_, az_ = buf[0], buf[1], buf[2]
                    e1, e2, e3 = ex, ey, ez
                    f1, f2, f3 = fx, fy, fz
                    if src.has_port:
                        ea = e1 * ax_ + e2 * ay_ + e3 * az_
                        e1, e2, e3 = carry_frame(e1 - ea * ax_, e2 - ea * ay_, e3 - ea * az_, ax_, ay_, az_,
                                                 wx, wy, wz, nx, ny, nz)
                        fa = f1 * ax_ + f2 * ay_ + f3 * az_
                        f1, f2, f3 = carry_frame(f1 - fa * ax_, f2 - fa * ay_, f3 - fa * az_, ax_, ay_, az_,
                                                 wx, wy, wz, nx, ny, nz)
                    aa, bb = e1 * ix + e2 * iy + e3 * iz, e1 * pxx + e2 * pyy + e3 * pzz
                    af, bf = f1 * ix + f2 * iy + f3 * iz, f1 * pxx + f2 * pyy + f3 * pzz
                    c2, s2, v2 = source_state(aa, bb, af, bf, pol.qwp)
                    q_in, u_in, v_in = pol.dop_l * c2, pol.dop_l * s2, pol.dop_l * v2
                    if dia:
                        val, q_in, u_in, v_in = _through_source_port(src, ax_, ay_, az_, wx, wy, wz, ix, iy,
                                                                     iz, pxx, pyy, pzz, val, q_in, u_in, v_in)
                        if not (pol.mueller or pol.on):
                            b_ray += val
                            continue
                    m22 = depol_big * 0.75 * (1.0 + mu * mu)
                    m11 = m22 + (1.0 - depol_big)
                    m12 = -depol_big * 0.75 * (omm * opm)
                    m33 = depol_big * 1.5 * mu
                    i_out = m11 + m12 * q_in
                    if pol.mueller:
                        val *= i_out / m11
                    b_ray += val
                    if not pol.on:
                        continue
                    qs = (m12 + m22 * q_in) / i_out
                    us = m33 * u_in / i_out
                    # e_par_out = e_perp × (−d), its angle β from the camera's r toward its u
                    ox_, oy_, oz_ = -(pyy * dz - pzz * dy), -(pzz * dx - pxx * dz), -(pxx * dy - pyy * dx)
                    cx = ox_ * cam_r[kc, 0] + oy_ * cam_r[kc, 1] + oz_ * cam_r[kc, 2]
                    cy = ox_ * cam_u[kc, 0] + oy_ * cam_u[kc, 1] + oz_ * cam_u[kc, 2]
                    r2 = cx * cx + cy * cy
                    c, s = ((cx * cx - cy * cy) / r2, 2.0 * cx * cy / r2) if r2 > 0 else (1.0, 0.0)
                    q_ray += val * (qs * c - us * s)
                    u_ray += val * (qs * s + us * c)
                    if pol.qwp:
                        v_ray += val * big44 * 1.5 * mu * v_in / i_out
        b_out[i] = b_ray
        if pol.on:
            q_out[i], u_out[i], v_out[i] = q_ray, u_ray, v_ray
