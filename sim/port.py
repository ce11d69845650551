"""Rays through a flat refractive port (docs/physics.md §11): Snell at both faces, the Fresnel loss, and the
inverse, the air ray that reaches a given point in the water.

A port (:class:`~polarstripe.sim.scene_port.Port`) has its inner face at distance d and its outer face at
d + t from the pinhole P along the unit normal N: air (index n_a) before d, glass (n_g) between, water (n_w)
beyond. A ray in the plane of N and the radial unit vector e keeps Snell's invariant q = n_a·sin θ_a =
n_g·sin θ_g = n_w·sin θ_w, so with c_k = √(n_k² − q²) (c_k/n_k = cos θ_k, q/c_k = tan θ_k):

* forward (a camera pixel): the air ray a meets the inner face, refracts into the glass and into the water;
  the water ray starts on the outer face at E = P + (d + t)·N + q·(d/c_a + t/c_g)·e and runs along
  w = (c_w·N + q·e)/n_w;
* inverse (the projector's light reaching a water point Y at height z = (Y − P)·N above P, radial distance
  ρ): q solves r(q) = q·(d/c_a + t/c_g + ℓ/c_w) = ρ with ℓ = z − d − t, an increasing function that grows
  without bound as q nears the least index n_m; Newton's method runs in τ = q/c_m (q = n_m·τ/√(1 + τ²)),
  where the term of the least index is linear and the others are bounded (in q, points far off the axis
  took ~20 steps), kept inside the bracket of the signs seen so far, from a nearby point's q (the previous
  node on a ray) or the paraxial q₀ = ρ/(d/n_a + t/n_g + ℓ/n_w): ~3–6 steps to rounding;
* the irradiance a point source of intensity I₀ [W/sr] in the air gives at Y, per unit area normal to w, is
  I₀·T·J with J = dΩ_a/dA_⊥ = 1/(n_a²·cos θ_a·cos θ_w·r'(q)·r(q)/q): with no port (every index 1) J =
  cos²θ/z² = 1/|Y − P|²; at normal incidence through a vanishing port J = (n_w/n_a)²/z², the solid angle
  compressed by n² (the radiance theorem: L/n² is conserved along a ray);
* T: Fresnel transmittance of unpolarized light through both faces, ½(T_s + T_p) with T_s = T_s1·T_s2,
  T_p = T_p1·T_p2 (1 for a coated port; multiple reflections inside the glass are neglected), and the
  radiance a camera behind the port sees of water radiance L_w is L_w·T·(n_a/n_w)²;
* the port's diattenuation: in the frame of the plane of incidence (Q = I_p − I_s, p the axis in the plane
  of N and the ray) the port is the Mueller matrix ½[[T_p + T_s, T_p − T_s, 0, 0], [T_p − T_s, T_p + T_s, 0,
  0], [0, 0, 2√(T_p T_s), 0], [0, 0, 0, 2√(T_p T_s)]] (no retardance below the critical angle), its m00 the
  T above (:func:`diattenuate`). The frame is carried through each face: its s axis kept, its p axis
  turned with the ray (:func:`carry_frame`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit


class PortGeometry(NamedTuple):
    """A port placed in the world: pinhole ``apex`` (3,), unit ``normal`` (3,), inner-face distance ``d`` and
    glass thickness ``t`` [m], indices ``n_a``, ``n_g``, ``n_w``, and ``fresnel`` (False: coated)."""

    apex: np.ndarray
    normal: np.ndarray
    d: float
    t: float
    n_a: float
    n_g: float
    n_w: float
    fresnel: bool


def port_geometry(port, position, forward) -> PortGeometry:
    """The :class:`PortGeometry` of ``port`` on a device at ``position`` looking along ``forward``."""
    n = np.asarray(forward if port.normal is None else port.normal, float)
    return PortGeometry(np.asarray(position, float).copy(), n / np.linalg.norm(n), float(port.distance_m),
                        float(port.thickness_m), float(port.n_air), float(port.n_glass), float(port.n_water),
                        not port.coated)


@njit(cache=True, nogil=True)
def _interface(ci, ct, n1, n2):
    """Fresnel power transmittances (T_s, T_p) from index n1 to n2, cosines ci (incident), ct (refracted)."""
    rs = (n1 * ci - n2 * ct) / (n1 * ci + n2 * ct)
    rp = (n2 * ci - n1 * ct) / (n2 * ci + n1 * ct)
    return 1.0 - rs * rs, 1.0 - rp * rp


@njit(cache=True, nogil=True)
def transmittances_sp(q, t, n_a, n_g, n_w, fresnel):
    """(T_s, T_p) = (T_s1·T_s2, T_p1·T_p2) through both faces at Snell invariant q (one air–water face when
    t = 0; (1, 1) for a coated port)."""
    if not fresnel:
        return 1.0, 1.0
    ca = math.sqrt(max(n_a * n_a - q * q, 0.0)) / n_a
    cw = math.sqrt(max(n_w * n_w - q * q, 0.0)) / n_w
    if t <= 0.0:
        return _interface(ca, cw, n_a, n_w)
    cg = math.sqrt(max(n_g * n_g - q * q, 0.0)) / n_g
    ts1, tp1 = _interface(ca, cg, n_a, n_g)
    ts2, tp2 = _interface(cg, cw, n_g, n_w)
    return ts1 * ts2, tp1 * tp2


@njit(cache=True, nogil=True)
def transmittance(q, d, t, n_a, n_g, n_w, fresnel):
    """½(T_s1·T_s2 + T_p1·T_p2) through both faces at Snell invariant q (one air–water face when t = 0)."""
    ts, tp = transmittances_sp(q, t, n_a, n_g, n_w, fresnel)
    return 0.5 * (ts + tp)


@njit(cache=True, nogil=True)
def diattenuate(ts, tp, c2, s2, i, q, u, v):
    """The port's Mueller matrix (module docstring) applied to the Stokes vector (i, q, u, v) given in a frame
    where the port's p axis lies at angle θ (c2, s2 = cos 2θ, sin 2θ): the vector rotated into the p/s frame
    (q_p = c2·q + s2·u, u_p = −s2·q + c2·u), i' = ½(T_p + T_s)·i + ½(T_p − T_s)·q_p,
    q_p' = ½(T_p − T_s)·i + ½(T_p + T_s)·q_p, u_p' = √(T_p T_s)·u_p, v' = √(T_p T_s)·v, rotated back.
    Works on floats and on arrays alike."""
    mean, half, root = 0.5 * (tp + ts), 0.5 * (tp - ts), np.sqrt(tp * ts)
    qp, up = c2 * q + s2 * u, c2 * u - s2 * q
    qp2, up2 = half * i + mean * qp, root * up
    return mean * i + half * qp, c2 * qp2 - s2 * up2, s2 * qp2 + c2 * up2, root * v


@njit(cache=True, nogil=True)
def p_axis(ax, ay, az, nx, ny, nz):
    """The p axis s × a of the plane of incidence of air ray a on a port of normal n, s = normalize(a × n);
    (0, 0, 0) at normal incidence (no plane: T_s = T_p there)."""
    sx, sy, sz = ay * nz - az * ny, az * nx - ax * nz, ax * ny - ay * nx
    sn = math.sqrt(sx * sx + sy * sy + sz * sz)
    if sn < 1e-15:
        return 0.0, 0.0, 0.0
    sx, sy, sz = sx / sn, sy / sn, sz / sn
    return sy * az - sz * ay, sz * ax - sx * az, sx * ay - sy * ax


@njit(cache=True, nogil=True)
def _radial(q, d, t, ell, n_a, n_g, n_w):
    """r(q)/q and r'(q) (module docstring)."""
    ca = math.sqrt(n_a * n_a - q * q)
    cw = math.sqrt(n_w * n_w - q * q)
    s = d / ca + ell / cw
    ds = d * n_a * n_a / (ca * ca * ca) + ell * n_w * n_w / (cw * cw * cw)
    if t > 0.0:
        cg = math.sqrt(n_g * n_g - q * q)
        s += t / cg
        ds += t * n_g * n_g / (cg * cg * cg)
    return s, ds


_Q_MAX = 1.0 - 1e-12           # q/n_m at most: an air or water ray within ~1e-6 rad of the port's plane
_TAU_MAX = _Q_MAX / math.sqrt(1.0 - _Q_MAX * _Q_MAX)


@njit(cache=True, nogil=True)
def solve_invariant(rho, ell, d, t, n_a, n_g, n_w, hint=0.0):
    """Snell's invariant q of the ray from the pinhole to a water point at radial distance ``rho`` and
    ``ell`` beyond the outer face (module docstring), from the start ``hint`` (a nearby point's q; ≤ 0: the
    paraxial q₀)."""
    if rho <= 0.0:
        return 0.0
    n_m = min(n_a, n_w)
    if t > 0.0:
        n_m = min(n_m, n_g)
    q = hint if 0.0 < hint < _Q_MAX * n_m else min(rho / (d / n_a + t / n_g + ell / n_w), 0.999 * n_m)
    tau = q / math.sqrt(n_m * n_m - q * q)
    lo, hi, capped = 0.0, _TAU_MAX, False
    for _ in range(200):
        den = math.sqrt(1.0 + tau * tau)
        q = n_m * tau / den
        s, ds = _radial(q, d, t, ell, n_a, n_g, n_w)
        f = q * s - rho
        if f == 0.0:
            return q
        if f > 0.0:
            hi = tau
        elif tau >= _TAU_MAX:               # the root lies beyond the grazing limit: stop there
            return q
        else:
            lo = tau
        step = f * den * den * den / (ds * n_m)
        if abs(step) <= 1e-11 * tau:          # quadratic convergence: the next step is below rounding
            tau -= step
            break
        tau -= step
        if not lo < tau < hi:
            tau = 0.5 * (lo + hi) if hi < _TAU_MAX or capped else _TAU_MAX
            capped = capped or tau == _TAU_MAX
    return n_m * tau / math.sqrt(1.0 + tau * tau)


@njit(cache=True, nogil=True)
def through_port(px, py, pz, geo_apex, geo_n, d, t, n_a, n_g, n_w, fresnel, out):
    """The light from the pinhole reaching the water point (px, py, pz): out[0:3] the air direction a,
    out[3:6] the exit point E on the outer face, out[6:9] the water direction w, out[9] J [1/m²], out[10] T,
    out[11] Snell's invariant q (read first as the solver's start: 0, or the q of a nearby point).
    Returns False when the point is not beyond the outer face (then nothing reaches it)."""
    vx, vy, vz = px - geo_apex[0], py - geo_apex[1], pz - geo_apex[2]
    nx, ny, nz = geo_n[0], geo_n[1], geo_n[2]
    z = vx * nx + vy * ny + vz * nz
    ell = z - d - t
    if not ell > 0.0:
        return False
    rx, ry, rz = vx - z * nx, vy - z * ny, vz - z * nz
    rho = math.sqrt(rx * rx + ry * ry + rz * rz)
    if rho > 0.0:
        ex, ey, ez = rx / rho, ry / rho, rz / rho
    else:
        ex, ey, ez = 0.0, 0.0, 0.0
    q = solve_invariant(rho, ell, d, t, n_a, n_g, n_w, out[11])
    out[11] = q
    ca = math.sqrt(n_a * n_a - q * q)
    cw = math.sqrt(n_w * n_w - q * q)
    s, ds = _radial(q, d, t, ell, n_a, n_g, n_w)
    lateral = d / ca + (t / math.sqrt(n_g * n_g - q * q) if t > 0.0 else 0.0)
    out[0], out[1], out[2] = (ca * nx + q * ex) / n_a, (ca * ny + q * ey) / n_a, (ca * nz + q * ez) / n_a
    out[3] = geo_apex[0] + (d + t) * nx + q * lateral * ex
    out[4] = geo_apex[1] + (d + t) * ny + q * lateral * ey
    out[5] = geo_apex[2] + (d + t) * nz + q * lateral * ez
    out[6], out[7], out[8] = (cw * nx + q * ex) / n_w, (cw * ny + q * ey) / n_w, (cw * nz + q * ez) / n_w
    out[9] = 1.0 / (n_a * n_a * (ca / n_a) * (cw / n_w) * ds * s)
    out[10] = transmittance(q, d, t, n_a, n_g, n_w, fresnel)
    return True


@njit(cache=True, nogil=True)
def carry_frame(vx, vy, vz, ax, ay, az, wx, wy, wz, nx, ny, nz):
    """A transverse vector v of the air ray a carried to the water ray w through the port (normal n): its
    component along s = normalize(a × n) kept, its component along p(a) = s × a put on p(w) = s × w."""
    sx, sy, sz = ay * nz - az * ny, az * nx - ax * nz, ax * ny - ay * nx
    sn = math.sqrt(sx * sx + sy * sy + sz * sz)
    if sn < 1e-15:
        return vx, vy, vz
    sx, sy, sz = sx / sn, sy / sn, sz / sn
    pax, pay, paz = sy * az - sz * ay, sz * ax - sx * az, sx * ay - sy * ax
    pwx, pwy, pwz = sy * wz - sz * wy, sz * wx - sx * wz, sx * wy - sy * wx
    cs = vx * sx + vy * sy + vz * sz
    cp = vx * pax + vy * pay + vz * paz
    return cs * sx + cp * pwx, cs * sy + cp * pwy, cs * sz + cp * pwz


@njit(cache=True, nogil=True)
def _forward_kernel(dirs, apex, n, d, t, n_a, n_g, n_w, fresnel, axes, origins, water, trans, axes_out):
    for i in range(dirs.shape[0]):
        ax, ay, az = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        c = ax * n[0] + ay * n[1] + az * n[2]
        rx, ry, rz = ax - c * n[0], ay - c * n[1], az - c * n[2]
        sin_a = math.sqrt(rx * rx + ry * ry + rz * rz)
        q = n_a * sin_a
        ex, ey, ez = (rx / sin_a, ry / sin_a, rz / sin_a) if sin_a > 0.0 else (0.0, 0.0, 0.0)
        ca = math.sqrt(n_a * n_a - q * q)
        cw = math.sqrt(n_w * n_w - q * q)
        lateral = d / ca + (t / math.sqrt(n_g * n_g - q * q) if t > 0.0 else 0.0)
        for k in range(3):
            e_k = ex if k == 0 else (ey if k == 1 else ez)
            origins[i, k] = apex[k] + (d + t) * n[k] + q * lateral * e_k
            water[i, k] = (cw * n[k] + q * e_k) / n_w
        trans[i] = transmittance(q, d, t, n_a, n_g, n_w, fresnel)
        for m in range(axes.shape[0]):
            vx, vy, vz = carry_frame(axes[m, 0], axes[m, 1], axes[m, 2], ax, ay, az, water[i, 0], water[i, 1],
                                     water[i, 2], n[0], n[1], n[2])
            axes_out[m, i, 0], axes_out[m, i, 1], axes_out[m, i, 2] = vx, vy, vz


def water_rays(geo: PortGeometry, air_dirs: np.ndarray, axes: np.ndarray | None = None):
    """The water rays of air rays ``air_dirs`` (n, 3) unit from the pinhole (each within 90° of the normal).

    Returns
    -------
    origins (n, 3) on the outer face, dirs (n, 3) unit in the water, T (n,) the Fresnel transmittance, and the
    ``axes`` (m, 3) (the camera's r, u) carried through the port per ray, (m, n, 3).
    """
    air_dirs = np.ascontiguousarray(air_dirs, float)
    n = air_dirs.shape[0]
    axes = np.zeros((0, 3)) if axes is None else np.ascontiguousarray(axes, float)
    origins, water, trans = np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
    axes_out = np.empty((axes.shape[0], n, 3))
    _forward_kernel(air_dirs, geo.apex, geo.normal, geo.d, geo.t, geo.n_a, geo.n_g, geo.n_w, geo.fresnel,
                    axes,
                    origins, water, trans, axes_out)
    return origins, water, trans, axes_out


@njit(cache=True, nogil=True)
def _inverse_kernel(points, apex, n, d, t, n_a, n_g, n_w, fresnel, out, ok):
    buf = np.zeros(12)
    for i in range(points.shape[0]):
        ok[i] = through_port(points[i, 0], points[i, 1], points[i, 2], apex, n, d, t, n_a, n_g, n_w, fresnel,
                             buf)
        for k in range(11):
            out[i, k] = buf[k] if ok[i] else np.nan


class PortLight(NamedTuple):
    """The light from a pinhole reaching water points through its port: air directions ``air`` (n, 3), exit
    points ``exit`` (n, 3), water directions ``water`` (n, 3), ``J`` (n,) [1/m²], ``T`` (n,), ``ok`` (n,)
    (False: the point is not beyond the outer face; the others are NaN there)."""

    air: np.ndarray
    exit: np.ndarray
    water: np.ndarray
    J: np.ndarray
    T: np.ndarray
    ok: np.ndarray


def light_to(geo: PortGeometry, points: np.ndarray) -> PortLight:
    """The inverse of :func:`water_rays` for water ``points`` (n, 3): which air ray reaches each, where it
    leaves the port, along which water direction, and the irradiance factor J (module docstring)."""
    points = np.ascontiguousarray(points, float).reshape(-1, 3)
    out, ok = np.empty((points.shape[0], 11)), np.empty(points.shape[0], bool)
    _inverse_kernel(points, geo.apex, geo.normal, geo.d, geo.t, geo.n_a, geo.n_g, geo.n_w, geo.fresnel, out,
                    ok)
    return PortLight(out[:, 0:3], out[:, 3:6], out[:, 6:9], out[:, 9], out[:, 10], ok)


def radiance_factor(geo: PortGeometry, trans: np.ndarray) -> np.ndarray:
    """The camera-side factor T·(n_a/n_w)²: air radiance behind the port per unit water radiance."""
    return trans * (geo.n_a / geo.n_w) ** 2


@njit(cache=True, nogil=True)
def _camera_mueller_kernel(dirs, n, n_a, t, n_g, n_w, fresnel, r, u, out):
    for i in range(dirs.shape[0]):
        ax, ay, az = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        c = ax * n[0] + ay * n[1] + az * n[2]
        q = n_a * math.sqrt(max(1.0 - c * c, 0.0))
        out[i, 0], out[i, 1] = transmittances_sp(q, t, n_a, n_g, n_w, fresnel)
        px, py, pz = p_axis(ax, ay, az, n[0], n[1], n[2])
        cx, cy = px * r[0] + py * r[1] + pz * r[2], px * u[0] + py * u[1] + pz * u[2]
        r2 = cx * cx + cy * cy
        out[i, 2], out[i, 3] = ((cx * cx - cy * cy) / r2, 2.0 * cx * cy / r2) if r2 > 0.0 else (1.0, 0.0)


class PortMueller(NamedTuple):
    """The port's Mueller matrix per camera ray (:func:`diattenuate`): ``ts``, ``tp`` (n,) and the p axis's
    angle θ in the camera frame (from image right toward image up) as ``c2``, ``s2`` = cos 2θ, sin 2θ (n,)."""

    ts: np.ndarray
    tp: np.ndarray
    c2: np.ndarray
    s2: np.ndarray


def camera_mueller(geo: PortGeometry, air_dirs: np.ndarray, r, u) -> PortMueller:
    """:class:`PortMueller` of a camera's air rays ``air_dirs`` (n, 3) through its port; ``r``, ``u`` the
    camera's right and up axes. The p axis of each ray is radial in the image about the port's normal."""
    air_dirs = np.ascontiguousarray(air_dirs, float).reshape(-1, 3)
    out = np.empty((air_dirs.shape[0], 4))
    _camera_mueller_kernel(air_dirs, geo.normal, geo.n_a, geo.t, geo.n_g, geo.n_w, geo.fresnel,
                           np.asarray(r, float), np.asarray(u, float), out)
    return PortMueller(*out.T)
