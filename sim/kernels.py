"""Compiled (numba) inner loops of the light-transport model: the eq. 13 line integral per lit interval.

:func:`line_integrals` is the per-interval body of :func:`polarstripe.sim.transport.line_radiance`, written
as one loop: split each interval where the scattering angle crosses the forward lobe and where the excess
optical path passes 6, 12, 24, 48 e-folds, pick the Gauss–Legendre node count, truncate at 50 excess optical
depths, sum in log space in the θ / φ form of the ξ-substitution (docs/physics.md §2.2) and accumulate the
scattering-plane Stokes on a subset of the nodes (the steps are documented in ``transport``; the arithmetic
is that of the numpy code this replaced, node for node). Also here: the clip of rays to the pattern's
half-spaces, D (eq. 11) and the rotation of the Stokes sums into the camera frame. No ``fastmath`` (the
reference tests compare to 1e-6; it bought 8 %). Compiled once per machine (``cache=True``, ``__pycache__``).
The arguments are the records of :mod:`polarstripe.sim.kernel_records`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from polarstripe.sim.stokes_kernels import m12_over_m11, source_state

_FOUR_PI = 4.0 * math.pi
_G_MAX = 1.0 - 1e-6


@njit(cache=True, nogil=True)
def _hg(omm, opm, g):
    if g > _G_MAX:
        g = _G_MAX
    elif g < -_G_MAX:
        g = -_G_MAX
    if g >= 0:
        den = (1.0 - g) ** 2 + 2.0 * g * max(omm, 0.0)
    else:
        den = (1.0 + g) ** 2 - 2.0 * g * max(opm, 0.0)
    return (1.0 - g) * (1.0 + g) / (_FOUR_PI * den * math.sqrt(den))


@njit(cache=True, nogil=True)
def phase_value(phase, omm, opm):
    """P [1/sr] of a ``PhaseArgs`` record given 1 − μ and 1 + μ."""
    if phase.code == 0:
        return 1.0 / _FOUR_PI
    if phase.code == 1:
        return _hg(omm, opm, phase.g1)
    if phase.code == 3:                  # the scaled P̃: the forward cone 1 − μ < cut is cut out
        if omm < phase.cut:
            return 0.0
        return phase.norm * (phase.alpha * _hg(omm, opm, phase.g1)
                             + (1.0 - phase.alpha) * _hg(omm, opm, -phase.g2))
    if phase.code == 4:                  # the forward cone alone
        if omm >= phase.cut:
            return 0.0
        return phase.alpha * _hg(omm, opm, phase.g1) + (1.0 - phase.alpha) * _hg(omm, opm, -phase.g2)
    return phase.alpha * _hg(omm, opm, phase.g1) + (1.0 - phase.alpha) * _hg(omm, opm, -phase.g2)


@njit(cache=True, nogil=True)
def unit_normal(ax, ay, az, dx, dy, dz, tol):
    """normalize(a × d), or a unit vector ⊥ d when |a × d| ≤ tol (a on the ray: any scattering plane)."""
    px, py, pz = ay * dz - az * dy, az * dx - ax * dz, ax * dy - ay * dx
    pn = math.sqrt(px * px + py * py + pz * pz)
    if pn > tol:
        return px / pn, py / pn, pz / pn
    if abs(dx) < 0.9:
        hx, hy, hz = 1.0, 0.0, 0.0
    else:
        hx, hy, hz = 0.0, 1.0, 0.0
    px, py, pz = dy * hz - dz * hy, dz * hx - dx * hz, dx * hy - dy * hx
    pn = math.sqrt(px * px + py * py + pz * pz)
    return px / pn, py / pn, pz / pn


@njit(cache=True, nogil=True)
def segment_in_box(ax, ay, az, bx, by, bz, lo, hi):
    """Length [m] of the segment a→b inside the box [lo, hi] (as geometry.segment_length_in_box)."""
    vx, vy, vz = bx - ax, by - ay, bz - az
    length = math.sqrt(vx * vx + vy * vy + vz * vz)
    if length <= 0.0:
        return 0.0
    t0, t1 = -1e30, 1e30
    for k in range(3):
        o = ax if k == 0 else (ay if k == 1 else az)
        v = (vx if k == 0 else (vy if k == 1 else vz)) / length
        if v == 0.0:
            if o < lo[k] or o > hi[k]:
                return 0.0
            continue
        ta, tb = (lo[k] - o) / v, (hi[k] - o) / v
        t0 = max(t0, min(ta, tb))
        t1 = min(t1, max(ta, tb))
    t0 = max(t0, 0.0)
    return max(min(t1, length) - t0, 0.0)


@njit(cache=True, nogil=True)
def line_integrals(light, medium, phase, quad, polarization, rays, intervals, out):
    """Accumulate the eq. 13 line integral of each interval into its ray (see the module docstring).

    Arguments are the records of :mod:`~polarstripe.sim.kernel_records` (``Light``, ``Medium``,
    ``PhaseArgs``, ``Quadrature``, ``Polarization``, ``Rays``, ``Intervals``); the sums are added into ``out``
    (``Stokes``; q and u only with ``polarization.on``).
    """
    src_pos, radius, inten, inside, facing = light
    st, ss, box_lo, box_hi = medium
    nodes, gl_t, gl_w, gl_n, sub_all, nsubs, width, split_alphas = quad
    pol, mueller, reverse, e_field, dop_l, depol, dsigma, fast_axis, dsigma_v = polarization
    big = (1.0 - depol) / (1.0 + depol / 2.0)
    big44 = big * (1.0 - 2.0 * depol) / (1.0 - depol) if depol < 1.0 else 0.0    # Hansen & Travis: ΔΔ'
    fx, fy, fz = fast_axis[0], fast_axis[1], fast_axis[2]
    qwp = fx * fx + fy * fy + fz * fz > 0.0
    origin, dirs, view_start = rays
    ray, lo, hi = intervals
    b_out, q_out, u_out, v_out = out
    nmax = gl_t.shape[1]
    ang = np.empty(nmax)
    uu = np.empty(nmax)
    dly = np.empty(nmax)
    omm_a = np.empty(nmax)
    opm_a = np.empty(nmax)
    wk = np.empty(nmax)
    leg_l = np.zeros(nmax)       # a node's in-medium distances from the source and to the camera
    leg_c = np.zeros(nmax)
    edges = np.empty(split_alphas.size + 2)
    per_src = src_pos.shape[0] > 1
    per_org = origin.shape[0] > 1
    use_facing = facing.shape[0] > 0
    per_face = facing.shape[0] > 1
    tan3, tan075 = math.tan(min(0.25, 3 * width)), math.tan(min(0.06, 0.75 * width))
    split_cot = np.empty(split_alphas.size)
    for k in range(split_alphas.size):
        split_cot[k] = 1.0 / math.tan(split_alphas[k])
    ex, ey, ez = e_field[0], e_field[1], e_field[2]
    for j in range(ray.size):
        r = ray[j]
        ks = r if per_src else 0
        ko = r if per_org else 0
        sx, sy, sz = src_pos[ks, 0], src_pos[ks, 1], src_pos[ks, 2]
        cx, cy, cz = origin[ko, 0], origin[ko, 1], origin[ko, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        lx, ly, lz = sx - cx, sy - cy, sz - cz
        xc = lx * dx + ly * dy + lz * dz
        hx, hy, hz = lx - xc * dx, ly - xc * dy, lz - xc * dz
        h2 = hx * hx + hy * hy + hz * hz
        he = max(math.sqrt(h2 + radius * radius), 1e-200)
        he_split = math.sqrt(max(lx * lx + ly * ly + lz * lz - xc * xc, 0.0) + radius * radius)
        nfx = nfy = nfz = 0.0
        if use_facing:
            kf = r if per_face else 0
            nfx, nfy, nfz = facing[kf, 0], facing[kf, 1], facing[kf, 2]
        a0, a1 = lo[j], hi[j]
        bb = hw = dw = bf = hwf = dwf = 0.0
        if pol or mueller:
            # scattering-plane frame of the ray: e_perp = normalize(hvec × d) (any ⊥ when L is on the ray);
            # the incident E-field's components: bb normal to the plane, aa in it (per node, or dw reversed);
            # the same for the quarter-wave plate's fast axis (bf, af)
            px, py, pz = unit_normal(hx, hy, hz, dx, dy, dz, 1e-12 * math.sqrt(h2))
            bb = px * ex + py * ey + pz * ez
            wx, wy, wz = ey * pz - ez * py, ez * px - ex * pz, ex * py - ey * px         # E × e_perp
            hw, dw = hx * wx + hy * wy + hz * wz, dx * wx + dy * wy + dz * wz
            if qwp:
                bf = px * fx + py * fy + pz * fz
                wx, wy, wz = fy * pz - fz * py, fz * px - fx * pz, fx * py - fy * px
                hwf, dwf = hx * wx + hy * wy + hz * wz, dx * wx + dy * wy + dz * wz
        # split where the scattering angle crosses multiples of the forward-lobe width
        ne = 0
        edges[ne] = a0
        ne += 1
        for k in range(split_alphas.size):
            xb = xc - he_split * split_cot[k]
            if a0 < xb < a1:
                edges[ne] = xb
                ne += 1
        edges[ne] = a1
        ne += 1
        if ne > 3:
            edges[1:ne - 1].sort()
        b_ray = q_ray = u_ray = v_ray = 0.0
        vs = view_start[r]
        for p in range(ne - 1):
            x0, x1 = edges[p], edges[p + 1]
            if not x1 > x0:
                continue
            trunc = 50.0
            if st > 0.0:
                u0 = x0 - xc
                d0 = math.sqrt(u0 * u0 + h2)
                lim = min(trunc / st, 1e100)
                if inside:
                    s0 = d0 + u0 if u0 >= 0 else h2 / max(d0 - u0, 1e-300)
                    q = s0 + lim
                    x_tr = xc + (q * q - h2) / (2.0 * q)
                else:
                    x_tr = x0 + segment_in_box(sx, sy, sz, cx + x0 * dx, cy + x0 * dy, cz + x0 * dz, box_lo,
                                               box_hi) + lim
                x1 = min(x1, max(x_tr, x0))
            # a piece long in optical depth is cut where the excess path (rate ≤ 2σ_t) may reach 6, 12, 24, 48
            # e-folds, so each sub-piece's exponential is resolved by the rule whatever σ_t
            xa_end = x1
            n_sub = 1
            if st > 0.0:
                while n_sub < 5 and (x1 - x0) * 2.0 * st > 3.0 * 2.0 ** n_sub:
                    n_sub += 1
            for sp in range(n_sub):
                x0 = edges[p] if sp == 0 else x1
                x1 = xa_end if sp == n_sub - 1 else edges[p] + 3.0 * 2.0 ** (sp + 1) / (2.0 * st)
                rule = 0
                if nodes > 2:
                    # angle between the ends seen from the foot: tan(span) = num/den (span < π/2 iff den > 0)
                    hs = max(he_split, 1e-200)
                    num, den = (x1 - x0) * hs, hs * hs + (x1 - xc) * (x0 - xc)
                    tau = st * (x1 - x0)
                    if den > 0 and num < tan075 * den and tau < 0.5:
                        rule = 2
                    elif den > 0 and num < tan3 * den and tau < 2.0:
                        rule = 1
                u0, u1 = x0 - xc, x1 - xc
                if u0 >= 0:
                    side = 1.0
                    a_lo, a_hi = math.atan2(he, u1), math.atan2(he, u0)
                elif u1 <= 0:
                    side = -1.0
                    a_lo, a_hi = math.atan2(he, -u0), math.atan2(he, -u1)
                else:
                    side = 0.0
                    a_lo, a_hi = math.atan2(u0, he), math.atan2(u1, he)
                half = 0.5 * (a_hi - a_lo)
                mid = 0.5 * (a_hi + a_lo)
                m = 1e308
                for i in range(gl_n[rule]):
                    a = mid + half * gl_t[rule, i]
                    if side == 0.0:
                        u = he * math.tan(a)
                    else:
                        ta = math.tan(a)
                        u = side * he / ta if ta != 0.0 else math.inf
                    if not math.isfinite(u):
                        u = 0.0
                    x = xc + u
                    d_ly = math.sqrt(u * u + h2)
                    dsafe = max(d_ly, 1e-300)
                    if d_ly <= 0:
                        opm, omm = 1.0, 1.0
                    else:
                        opm = h2 / (dsafe * (d_ly + u) + 1e-300) if u > 0 else (d_ly - u) / dsafe
                        omm = h2 / (dsafe * (d_ly - u) + 1e-300) if u < 0 else (d_ly + u) / dsafe
                    uu[i], dly[i], omm_a[i], opm_a[i] = u, d_ly, omm, opm
                    if st > 0.0:
                        if inside:
                            light = d_ly
                        else:
                            light = segment_in_box(sx, sy, sz, cx + x * dx, cy + x * dy, cz + x * dz, box_lo,
                                                   box_hi)
                        e = st * (light + (x - vs))
                        leg_l[i], leg_c[i] = light, x - vs
                    else:
                        e = 0.0
                    ang[i] = e
                    if e < m:
                        m = e
                total = 0.0
                for i in range(gl_n[rule]):
                    v = gl_w[rule, i] * phase_value(phase, omm_a[i], opm_a[i]) * math.exp(-(ang[i] - m))
                    if mueller:     # I = P·(1 + m12/m11·Q_in): the matrix normalised by its m11 is P
                        dn = 1.0 if reverse else 1.0 / max(dly[i], 1e-300)
                        qn = source_state(dw if reverse else (-hw + uu[i] * dw) * dn, bb,
                                           dwf if reverse else (-hwf + uu[i] * dwf) * dn, bf, qwp)[0]
                        v *= 1.0 + m12_over_m11(omm_a[i], opm_a[i], big) * dop_l * qn
                    if use_facing:
                        cos_f = (-(hx * nfx + hy * nfy + hz * nfz) + uu[i] * (dx * nfx + dy * nfy + dz * nfz)
                                 ) / max(dly[i], 1e-300)
                        v *= max(cos_f, 0.0)
                    wk[i] = v
                    total += v
                if m < 600.0:
                    b = ss * inten / he * (abs(half) + 1e-300) * math.exp(-m) * total
                else:                   # log space: e^{−m} alone would underflow where 1/h_e is huge
                    b = math.exp(math.log(ss * inten) - math.log(he) + math.log(abs(half) + 1e-300)
                                 - m) * total
                b_ray += b
                if not pol:
                    continue
                tot = 0.0
                qs = 0.0
                us = 0.0
                vs = 0.0
                # a subset of the nodes, or with a plate every node: m44 ∝ μ changes sign at 90° along rays
                # that pass the source, which the subset does not resolve
                for jj in range(gl_n[rule] if qwp else nsubs[rule]):
                    i = jj if qwp else sub_all[rule, jj]
                    dn = 1.0 / max(dly[i], 1e-300)
                    c2, s2, v2 = source_state((-hw + uu[i] * dw) * dn, bb, (-hwf + uu[i] * dwf) * dn, bf,
                                               qwp)
                    q_in, u_in = dop_l * c2, dop_l * s2
                    omm, opm = omm_a[i], opm_a[i]
                    mu = 0.5 * (opm - omm)
                    m22 = big * 0.75 * (1.0 + mu * mu)
                    m11 = m22 + (1.0 - big)
                    m12 = -big * 0.75 * (omm * opm)
                    m33 = big * 1.5 * mu
                    i_out = m11 + m12 * q_in
                    tot += wk[i]
                    # the polarized part loses σ_p − σ̃_t on both legs; the polarization the scattering
                    # makes (m21 = m12) only on the way to the camera (docs/physics.md §10.4)
                    a_out = math.exp(-dsigma * leg_c[i]) if dsigma > 0.0 else 1.0
                    a_both = a_out * math.exp(-dsigma * leg_l[i]) if dsigma > 0.0 else 1.0
                    qs += wk[i] * (m12 * a_out + m22 * q_in * a_both) / i_out
                    us += wk[i] * m33 * u_in * a_both / i_out
                    if qwp:     # V' = m44·V (m34 = 0); the circular part loses σ_pV − σ̃_t on both legs
                        a_v = math.exp(-dsigma_v * (leg_c[i] + leg_l[i])) if dsigma_v > 0.0 else 1.0
                        vs += wk[i] * big44 * 1.5 * mu * dop_l * v2 * a_v / i_out
                if tot > 0:
                    q_ray += qs / tot * b
                    u_ray += us / tot * b
                    v_ray += vs / tot * b
        b_out[r] += b_ray
        if pol:
            q_out[r] += q_ray
            u_out[r] += u_ray
            v_out[r] += v_ray


@njit(cache=True, nogil=True)
def camera_stokes(src, origin, dirs, cr, cu, sums, q_out, u_out):
    """Rotate per-ray (q, u) of ``sums`` (a ``Stokes`` record) from the scattering-plane frame (e_par_out =
    e_perp × (−d)) into the camera's (r, u) axes ``cr``, ``cu`` (render._camera_stokes)."""
    b, q, u = sums.b, sums.q, sums.u
    lx, ly, lz = src[0] - origin[0], src[1] - origin[1], src[2] - origin[2]
    scale = math.sqrt(lx * lx + ly * ly + lz * lz)
    for i in range(dirs.shape[0]):
        if b[i] == 0.0 and q[i] == 0.0 and u[i] == 0.0:
            q_out[i] = 0.0
            u_out[i] = 0.0
            continue
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        px, py, pz = unit_normal(lx, ly, lz, dx, dy, dz, 1e-12 * max(scale, 1e-300))
        # e_par = e_perp × (−d)
        ax, ay, az = -(py * dz - pz * dy), -(pz * dx - px * dz), -(px * dy - py * dx)
        y = ax * cu[0] + ay * cu[1] + az * cu[2]            # e_par at angle β from r: cos 2β, sin 2β
        x = ax * cr[0] + ay * cr[1] + az * cr[2]
        r2 = x * x + y * y
        c, s = ((x * x - y * y) / r2, 2.0 * x * y / r2) if r2 > 0 else (1.0, 0.0)
        q_out[i] = q[i] * c - u[i] * s
        u_out[i] = q[i] * s + u[i] * c


@njit(cache=True, nogil=True)
def clip_rays(origin, dirs, x0, x1, apex, normals, eps, lo_out, hi_out):
    """[x0, x1] of rays origin + x·dir clipped to ∩ {n·(P − apex) ≥ 0} (patterns.clip_halfspaces); origin
    (1, 3) shared or (n, 3); a ray parallel to a plane (|n·d| ≤ eps·|n|) is kept or dropped whole."""
    per = origin.shape[0] > 1
    nn = np.empty(normals.shape[0])
    for k in range(normals.shape[0]):
        nn[k] = eps * math.sqrt(normals[k, 0] ** 2 + normals[k, 1] ** 2 + normals[k, 2] ** 2)
    for i in range(dirs.shape[0]):
        ko = i if per else 0
        rx, ry, rz = origin[ko, 0] - apex[0], origin[ko, 1] - apex[1], origin[ko, 2] - apex[2]
        a0, a1 = x0[i], x1[i]
        for k in range(normals.shape[0]):
            a = rx * normals[k, 0] + ry * normals[k, 1] + rz * normals[k, 2]
            b = dirs[i, 0] * normals[k, 0] + dirs[i, 1] * normals[k, 1] + dirs[i, 2] * normals[k, 2]
            if abs(b) <= nn[k]:
                if a < 0:
                    a1 = -math.inf
            elif b > 0:
                a0 = max(a0, -a / b)
            else:
                a1 = min(a1, -a / b)
        lo_out[i], hi_out[i] = a0, a1


@njit(cache=True, nogil=True)
def direct_kernel(light, medium, cam, surface, out):
    """D = (ρ cos φ/π)·I0·e^{−σ_t(ℓ_LO + ℓ_CO)}/(d_LO² + r_s²) at the lit ``SurfacePoints``, else 0
    (transport.direct); ``light.position`` is (1, 3), ``cam`` (3,)."""
    src, inten, radius = light.position[0], light.intensity, light.radius
    st, box_lo, box_hi = medium.sigma_t, medium.box_lo, medium.box_hi
    points, normals, albedo, lit = surface
    for i in range(points.shape[0]):
        if not lit[i]:
            out[i] = 0.0
            continue
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        vx, vy, vz = src[0] - px, src[1] - py, src[2] - pz
        d2 = vx * vx + vy * vy + vz * vz
        n_v = normals[i, 0] * vx + normals[i, 1] * vy + normals[i, 2] * vz
        cos_phi = max(n_v / max(math.sqrt(d2), 1e-300), 0.0)
        tau = st * (segment_in_box(src[0], src[1], src[2], px, py, pz, box_lo, box_hi)
                    + segment_in_box(cam[0], cam[1], cam[2], px, py, pz, box_lo, box_hi))
        out[i] = albedo[i] * cos_phi / math.pi * inten * math.exp(-tau) / max(d2 + radius * radius, 1e-300)
