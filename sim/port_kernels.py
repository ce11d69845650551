"""Compiled (numba) single scattering through flat ports (docs/physics.md §11): the eq. 13 line integral along
water rays whose light reaches each point through the projector's port.

Along a ray O + x·d over [x0, x1] (in the medium, before the first object):

    B = ∫ σ_s P(μ) I₀ T J e^{−σ_t (ℓ_L(Y) + x − x0)} (1 + m12/m11·DOP_L·q_in) lit(Y) dx,   μ = w·(−d)

with w, J, T and the exit point E of :func:`polarstripe.sim.port.through_port` (or, without a projector
port, w = (Y − L)/|Y − L|, J·T = 1/(|Y − L|² + r_s²), E = L), ℓ_L(Y) the length of E→Y inside the medium box,
and lit(Y) the pattern pixel of the air ray (a table of the pattern). The source is outside the water, so
the integrand has no 1/d² peak on the ray and is summed by Gauss–Legendre in x over the part of the ray
beyond the port's outer face. The lit pieces are found by subdividing the ray until at most one line of the
pattern where its lit state can change lies between the ends of a piece (:func:`lit_cuts`, each point's
state computed once), then solving for that line's crossing on each piece whose ends differ in lit state
(regula falsi on the pattern coordinate, nearly linear along the ray; :func:`_cut`). The Stokes sums are the
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
from polarstripe.sim.port import carry_frame, diattenuate, p_axis, transmittances_sp
from polarstripe.sim.port_cuts import light_at, lit_cuts, ray_state
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
    projector port with Fresnel faces (``PortSource.fresnel``) applies its Mueller matrix to the source.
    ``dsigma``, ``dsigma_v``: the extinction the linear and circular Stokes lose beyond σ_t (all orders'
    σ_p − σ̃_t, docs/physics.md §10.4: the response to the source's polarization on both legs, the
    polarization the scattering makes on the leg to the camera only; 0: single scattering)."""

    on: bool
    mueller: bool
    e_field: np.ndarray
    fast_axis: np.ndarray
    dop_l: float
    big: float
    big44: float
    qwp: bool
    dsigma: float = 0.0
    dsigma_v: float = 0.0


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
def needs_state(src, pol):
    """Whether :func:`node_stokes` needs the source's polarization state (the m12 term, the Stokes sums, or
    a polarized source through a Fresnel port)."""
    return pol.mueller or pol.on or (src.has_port and src.fresnel and pol.dop_l > 0.0)


@njit(cache=True, nogil=True)
def beyond_port(src, ox, oy, oz, dx, dy, dz, x0, x1):
    """[x0, x1] of the ray clipped to the points beyond the projector port's outer face (the light reaches
    no other; empty when hi ≤ lo)."""
    if not src.has_port:
        return x0, x1
    nx, ny, nz = src.normal[0], src.normal[1], src.normal[2]
    z0 = (ox - src.apex[0]) * nx + (oy - src.apex[1]) * ny + (oz - src.apex[2]) * nz
    dn = dx * nx + dy * ny + dz * nz
    face = src.d + src.t + 1e-12
    if dn > 0.0:
        return max(x0, (face - z0) / dn), x1
    if dn < 0.0:
        return x0, min(x1, (face - z0) / dn)
    return (x0, x1) if z0 > face else (x0, x0)


@njit(cache=True, nogil=True)
def node_stokes(src, pat, phase, pol, medium, stateful, ox, oy, oz, dx, dy, dz, x, x0, cam_r, cam_u, buf):
    """The point at x on the ray (camera-side path from x0): its (lit, col, row, valid) as :func:`light_at`
    and the integrand of B and of its camera-frame q, u, v there (module docstring; per unit length, the lit
    factor left out; zeros where no light reaches it). ``stateful``: the source's state is needed."""
    st, ss, box_lo, box_hi = medium
    px, py, pz = ox + x * dx, oy + x * dy, oz + x * dz
    lit, col, row, valid = light_at(src, pat, px, py, pz, buf)
    if not valid:
        return lit, col, row, valid, 0.0, 0.0, 0.0, 0.0
    wx, wy, wz = buf[6], buf[7], buf[8]
    mu = -(wx * dx + wy * dy + wz * dz)
    omm, opm = 1.0 - mu, 1.0 + mu
    ell = 0.0
    if st > 0.0:
        ell = segment_in_box(buf[3], buf[4], buf[5], px, py, pz, box_lo, box_hi)
    val = ss * src.intensity * buf[9] * phase_value(phase, omm, opm) * math.exp(-st * (ell + x - x0))
    if not stateful:
        return lit, col, row, valid, val, 0.0, 0.0, 0.0
    depol_big = pol.big
    nx, ny, nz = src.normal[0], src.normal[1], src.normal[2]
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
    e1, e2, e3 = pol.e_field[0], pol.e_field[1], pol.e_field[2]
    f1, f2, f3 = pol.fast_axis[0], pol.fast_axis[1], pol.fast_axis[2]
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
    if src.has_port and src.fresnel:           # the projector port's Mueller matrix on the source
        val, q_in, u_in, v_in = _through_source_port(src, ax_, ay_, az_, wx, wy, wz, ix, iy,
                                                     iz, pxx, pyy, pzz, val, q_in, u_in, v_in)
        if not (pol.mueller or pol.on):
            return lit, col, row, valid, val, 0.0, 0.0, 0.0
    m22 = depol_big * 0.75 * (1.0 + mu * mu)
    m11 = m22 + (1.0 - depol_big)
    m12 = -depol_big * 0.75 * (omm * opm)
    m33 = depol_big * 1.5 * mu
    i_out = m11 + m12 * q_in
    if pol.mueller:
        val *= i_out / m11
    if not pol.on:
        return lit, col, row, valid, val, 0.0, 0.0, 0.0
    if pol.dsigma > 0.0:          # σ_p: the made part on the camera leg, the rest on both legs
        a_out = math.exp(-pol.dsigma * (x - x0))
        a_both = a_out * math.exp(-pol.dsigma * ell)
        qs = (m12 * a_out + m22 * q_in * a_both) / i_out
        us = m33 * u_in * a_both / i_out
    else:
        qs = (m12 + m22 * q_in) / i_out
        us = m33 * u_in / i_out
    # e_par_out = e_perp × (−d), its angle β from the camera's r toward its u
    ox_, oy_, oz_ = -(pyy * dz - pzz * dy), -(pzz * dx - pxx * dz), -(pxx * dy - pyy * dx)
    cx = ox_ * cam_r[0] + oy_ * cam_r[1] + oz_ * cam_r[2]
    cy = ox_ * cam_u[0] + oy_ * cam_u[1] + oz_ * cam_u[2]
    r2 = cx * cx + cy * cy
    c, s = ((cx * cx - cy * cy) / r2, 2.0 * cx * cy / r2) if r2 > 0 else (1.0, 0.0)
    v_out = val * pol.big44 * 1.5 * mu * v_in / i_out if pol.qwp else 0.0
    if pol.dsigma_v > 0.0:
        v_out *= math.exp(-pol.dsigma_v * (ell + x - x0))
    return lit, col, row, valid, val, val * (qs * c - us * s), val * (qs * s + us * c), v_out


@njit(cache=True, nogil=True)
def ray_by_pieces(src, pat, medium, phase, pol, stateful, ox, oy, oz, dx, dy, dz, x0, lo, hi, cam_r, cam_u,
                  gl_t, gl_w, cuts, buf):
    """B, q, u, v of one ray over [lo, hi] (its camera-side path from x0): Gauss–Legendre on sub-pieces of
    each lit piece (:func:`lit_cuts`)."""
    st = medium[0]
    n_cut = lit_cuts(src, pat, ox, oy, oz, dx, dy, dz, lo, hi, cuts, buf)
    b_ray = q_ray = u_ray = v_ray = 0.0
    for p in range(n_cut + 1):
        a = lo if p == 0 else cuts[p - 1]
        b = hi if p == n_cut else cuts[p]
        if not b > a or not ray_state(src, pat, ox, oy, oz, dx, dy, dz, 0.5 * (a + b), buf)[0]:
            continue
        # sub-pieces: one per half optical depth and per 0.15 rad of the scattering angle's change
        wa = ray_state(src, pat, ox, oy, oz, dx, dy, dz, a, buf)[3]
        mua = -(buf[6] * dx + buf[7] * dy + buf[8] * dz) if wa else 0.0
        wb = ray_state(src, pat, ox, oy, oz, dx, dy, dz, b, buf)[3]
        mub = -(buf[6] * dx + buf[7] * dy + buf[8] * dz) if wb else 0.0
        turn = abs(math.acos(min(max(mua, -1.0), 1.0)) - math.acos(min(max(mub, -1.0), 1.0)))
        n_sub = min(64, 1 + int(st * (b - a) / 0.5) + int(turn / 0.15))
        for sp in range(n_sub):
            sa = a + (b - a) * sp / n_sub
            sb = a + (b - a) * (sp + 1) / n_sub
            half, mid = 0.5 * (sb - sa), 0.5 * (sb + sa)
            for k in range(gl_t.size):
                f = node_stokes(src, pat, phase, pol, medium, stateful, ox, oy, oz, dx, dy, dz,
                                mid + half * gl_t[k], x0, cam_r, cam_u, buf)
                wk = gl_w[k] * half
                b_ray += wk * f[4]
                q_ray += wk * f[5]
                u_ray += wk * f[6]
                v_ray += wk * f[7]
    return b_ray, q_ray, u_ray, v_ray
