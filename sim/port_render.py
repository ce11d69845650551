"""A frame through flat ports: single scattering (D, A, B and B's Stokes) with the camera's water rays and the
projector's light refracted at both faces of each port (docs/physics.md §11).

The camera's pixels look along their water rays (:func:`polarstripe.sim.port.water_rays`), starting on the
port's outer face; the radiance the camera sees is (n_a/n_w)² times the port's Mueller matrix applied to the
water radiance's Stokes vector (:func:`polarstripe.sim.port.diattenuate`: T for unpolarized light, and the
object's unpolarized light comes out polarized along each pixel's p axis, ``Sq``, ``Su``). The projector's
light reaches each water point along the air ray :func:`polarstripe.sim.port.light_to` finds, with irradiance
I₀·J times the port's Mueller matrix's intensity for the source's polarization (T when unpolarized); the
pattern pixel is that air ray's. D is eq. 11 with that irradiance, B the line integral of
:mod:`polarstripe.sim.port_kernels`, A the hemisphere integral of the same line integral at surface points (on
a grid of camera pixels, interpolated per object as :func:`polarstripe.sim.surface_field.a_field` does).
The higher orders through a port: :mod:`polarstripe.sim.port_higher`.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np
from polarstripe.sim.geometry import PinholeFrame, box_interval, intersect, pixel_rays, segment_length_in_box
from polarstripe.sim.geometry_cache import cached
from polarstripe.sim.kernel_records import Medium, Stokes
from polarstripe.sim.patterns import PatternSpec, pattern_lit
from polarstripe.sim.port import (
    PortMueller,
    camera_mueller,
    diattenuate,
    light_to,
    port_geometry,
    radiance_factor,
    water_rays,
)
from polarstripe.sim.port_kernels import (
    PatternTable,
    PortPolarization,
    PortSource,
    source_port_gain,
)
from polarstripe.sim.port_panels import port_line_integrals
from polarstripe.sim.scene import Scene
from polarstripe.sim.surface import surface_info
from polarstripe.sim.surface_field import camera_frame_stokes, interpolate_grid
from polarstripe.sim.threads import in_bands
from polarstripe.sim.transport import Source, gauss_legendre, hemisphere_directions, phase_args

_CAMERA_GRID = 3


def has_port(scene: Scene) -> bool:
    """True when the camera or the projector looks through a port."""
    return scene.camera.port is not None or scene.projector.port is not None


class PortView(NamedTuple):
    """The camera side through its port: water ray origins and directions (n, 3), the radiance factor
    T·(n_a/n_w)² (n,), the camera axes r, u carried into the water (n, 3) each, hits and surface info, and
    the port's Mueller matrix per ray (None: no port, or a coated one)."""

    origins: np.ndarray
    dirs: np.ndarray
    factor: np.ndarray
    cam_r: np.ndarray
    cam_u: np.ndarray
    hits: object
    surf: object
    mueller: PortMueller | None = None


def port_view(scene: Scene, cam: PinholeFrame, pixels) -> PortView:
    """The camera's water rays of ``pixels`` ((n, 2) (row, col), None: every pixel, row-major)."""
    air = pixel_rays(cam, pixels)
    port, mueller = scene.camera.port, None
    if port is None:
        n = air.shape[0]
        origins = np.broadcast_to(np.asarray(cam.position, float), (n, 3)).copy()
        dirs, factor = air, np.ones(n)
        cam_r, cam_u = np.broadcast_to(cam.r, (n, 3)).copy(), np.broadcast_to(cam.u, (n, 3)).copy()
    else:
        geo = port_geometry(port, cam.position, cam.f)
        origins, dirs, trans, axes = water_rays(geo, air, np.stack([cam.r, cam.u]))
        factor, cam_r, cam_u = radiance_factor(geo, trans), axes[0], axes[1]
        if geo.fresnel:
            mueller = camera_mueller(geo, air, cam.r, cam.u)
    hits = intersect(scene.objects, origins, dirs)
    return PortView(origins, dirs, factor, cam_r, cam_u, hits, surface_info(scene.objects, hits), mueller)


def _source(scene: Scene, src: Source) -> PortSource:
    pr = scene.projector
    forward = src.frame.f if src.frame is not None else np.subtract(pr.look_at, pr.position)
    if pr.port is None:
        return PortSource(np.asarray(src.position, float), np.zeros(3), 0.0, 0.0, 1.0, 1.0, 1.0, False, False,
                          float(src.radius), float(src.intensity))
    g = port_geometry(pr.port, pr.position, forward)
    return PortSource(g.apex, g.normal, g.d, g.t, g.n_a, g.n_g, g.n_w, g.fresnel, True, 0.0,
                      float(src.intensity))


@lru_cache(maxsize=8)
def _table(pattern: PatternSpec, w: int, h: int) -> np.ndarray:
    """The pattern's lit pixels (h, w) bool."""
    rows, cols = np.mgrid[0:h, 0:w]
    fake = PinholeFrame(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), 1.0, w, h)
    coords = ((cols + 0.5).ravel(), (rows + 0.5).ravel(), np.ones(w * h))
    lit = pattern_lit(pattern, fake, np.zeros((w * h, 3)), coords=coords).reshape(h, w)
    lit.flags.writeable = False
    return lit


def _cells(pattern: PatternSpec) -> np.ndarray:
    """(col offset, col size, row offset, row size) [pattern pixels]: cells whose boundaries hold every
    change of a checker's or Gray code's lit state (Gray bit b: the odd multiples of 2^b along its axis; an
    XOR base bit c, a column bit: the odd multiples of 2^c in columns; a column bit XOR its base: multiples
    of 2^min(b, c))."""
    if pattern.kind == "checker":
        return np.array([pattern.shift % pattern.size, pattern.size, 0.0, pattern.size], float)
    if pattern.kind == "gray":      # bit b changes at the odd multiples of 2^b
        off, size = float(2 ** pattern.index), float(2 ** (pattern.index + 1))
        if pattern.xor < 0:
            return np.array([off, size, 0.0, np.inf] if pattern.axis == "col" else [0.0, np.inf, off, size])
        base = float(2 ** pattern.xor)       # the XOR base, a column bit
        if pattern.axis == "col":
            return np.array([0.0, min(off, base), 0.0, np.inf])
        return np.array([base, 2.0 * base, off, size])
    return np.array([0.0, np.inf, 0.0, np.inf])


def _pattern(src: Source) -> PatternTable:
    fr = src.frame
    if fr is None:
        z = np.zeros(3)
        return PatternTable(z, z, z, 1.0, 1, 1, False, np.ones((1, 1), bool), _cells(src.pattern),
                            np.array([-np.inf, np.inf, -np.inf, np.inf]), True)
    table = _table(src.pattern, fr.w, fr.h)
    rows, cols = np.nonzero(table.any(axis=1))[0], np.nonzero(table.any(axis=0))[0]
    box = np.array([cols.min(), cols.max() + 1, rows.min(), rows.max() + 1], float) if rows.size else \
        np.array([0.0, 0.0, 0.0, 0.0])
    return PatternTable(fr.f, fr.r, fr.u, float(fr.s), int(fr.w), int(fr.h), True, table,
                        _cells(src.pattern), box, src.pattern.kind in ("flood", "stripe"))


def _polarization(src: Source, on: bool, diattenuating: bool) -> PortPolarization:
    """The kernel's polarization; ``diattenuating``: the projector's port has Fresnel faces, so even an
    unpolarized source reaches the water polarized and the m12 term is needed."""
    rayleigh = src.dop_model.model == "rayleigh"
    depol = float(src.dop_model.depolarization) if rayleigh else 0.0
    big = (1.0 - depol) / (1.0 + depol / 2.0)
    big44 = big * (1.0 - 2.0 * depol) / (1.0 - depol)
    extra = [0.0 if s is None or not on else max(float(s) - float(src.sigma_t), 0.0)
             for s in (src.sigma_pol, src.sigma_pol_v)]     # all orders' σ_p (docs/physics.md §10.4)
    return PortPolarization(bool(on and rayleigh), bool(rayleigh and (src.dop_l > 0.0 or diattenuating)),
                            np.asarray(src.e_field, float), np.asarray(src.fast_axis, float),
                            float(src.dop_l),
                            big, big44, bool(np.any(src.fast_axis)), *extra)


def line_stokes(scene: Scene, src: Source, origins, dirs, x0, x1, nodes: int, cam_r, cam_u, pol: bool):
    """B, q, u, v (camera frame) of rays origin + x·dir over [x0, x1] (:mod:`~polarstripe.sim.port_kernels`;
    a pattern of many lit pieces a ray, a Gray code or a checker, by :mod:`~polarstripe.sim.port_panels`).
    """
    n = dirs.shape[0]
    out = Stokes(np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n))
    if src.sigma_s <= 0.0 or src.intensity <= 0.0 or n == 0:
        return out
    t, w = gauss_legendre(max(int(nodes), 4))
    source, table = _source(scene, src), _pattern(src)
    args = (not table.convex, source, table,
            Medium(float(src.sigma_t), float(src.sigma_s), np.asarray(src.box_lo, float),
                   np.asarray(src.box_hi, float)), phase_args(src.phase),
            _polarization(src, pol, source.has_port and source.fresnel))
    f64 = np.ascontiguousarray
    origins, dirs = f64(origins, float).reshape(-1, 3), f64(dirs, float)
    x0, x1 = f64(np.broadcast_to(x0, (n,)), float), f64(np.broadcast_to(x1, (n,)), float)
    cam_r, cam_u = f64(cam_r, float).reshape(-1, 3), f64(cam_u, float).reshape(-1, 3)

    def band(a, b):
        o = origins[a:b] if origins.shape[0] > 1 else origins
        cr, cu = (cam_r[a:b], cam_u[a:b]) if cam_r.shape[0] > 1 else (cam_r, cam_u)
        port_line_integrals(*args, o, dirs[a:b], x0[a:b], x1[a:b], cr, cu, t, w,
                            Stokes(*(arr[a:b] for arr in out)))

    in_bands(n, band, min_size=512)
    return out


def _light(scene: Scene, src: Source, points: np.ndarray):
    """Air direction, exit point, water direction, J·T and validity of the light reaching ``points``; T is the
    port's Mueller matrix's intensity for the source's polarization (docs/physics.md §11)."""
    pr = scene.projector
    if pr.port is None:
        v = points - np.asarray(src.position, float)
        d2 = np.einsum("ij,ij->i", v, v)
        air = v / np.sqrt(np.maximum(d2, 1e-300))[:, None]
        exit_ = np.broadcast_to(np.asarray(src.position, float), points.shape)
        return air, exit_, air, 1.0 / np.maximum(d2 + src.radius ** 2, 1e-300), np.ones(len(points), bool)
    forward = src.frame.f if src.frame is not None else np.subtract(pr.look_at, pr.position)
    geo = port_geometry(pr.port, pr.position, forward)
    lt = light_to(geo, points)
    gain = np.ones(len(points))
    if geo.fresnel and src.dop_l > 0.0:
        air = np.ascontiguousarray(np.nan_to_num(lt.air))
        source_port_gain(air, geo.normal, geo.t, geo.n_a, geo.n_g, geo.n_w, np.asarray(src.e_field, float),
                         np.asarray(src.fast_axis, float), bool(np.any(src.fast_axis)), float(src.dop_l),
                         gain)
    return lt.air, lt.exit, lt.water, np.where(lt.ok, lt.J * lt.T * gain, 0.0), lt.ok


def port_direct(scene: Scene, src: Source, origins, points, normals, albedo) -> np.ndarray:
    """D (eq. 11) at surface points seen from camera-ray ``origins``, lit through the projector's port."""
    out = np.zeros(points.shape[0])
    if points.shape[0] == 0:
        return out
    air, exit_, water, jt, ok = _light(scene, src, points)
    fr = src.frame
    if fr is not None:
        depth = air @ fr.f
        with np.errstate(divide="ignore", invalid="ignore"):
            coords = (fr.w / 2.0 + (air @ fr.r) / depth / fr.s, fr.h / 2.0 - (air @ fr.u) / depth / fr.s,
                      depth)
        ok = ok & np.nan_to_num(pattern_lit(src.pattern, fr, points, coords=coords))
    idx = np.nonzero(ok)[0]
    v = points[idx] - exit_[idx]
    dist = np.linalg.norm(v, axis=1)
    hits = intersect(scene.objects, np.ascontiguousarray(exit_[idx]), v / np.maximum(dist, 1e-300)[:, None])
    idx = idx[~(hits.t < dist * (1.0 - 1e-9) - 1e-9)]
    cos_phi = np.clip(-np.einsum("ij,ij->i", normals[idx], water[idx]), 0.0, None)
    tau = src.sigma_t * (segment_length_in_box(exit_[idx], points[idx], src.box_lo, src.box_hi)
                         + segment_length_in_box(origins[idx], points[idx], src.box_lo, src.box_hi))
    out[idx] = albedo[idx] * cos_phi / np.pi * src.intensity * jt[idx] * np.exp(-tau)
    return out


def port_surface_scatter(scene: Scene, src: Source, origins, points, normals, albedo, fid) -> np.ndarray:
    """A (eq. 12, physical form) at surface points: (ρ/π)·e^{−σ_t ℓ_C} ∫ L_a(ω)(n·ω) dω with L_a the port line
    integral from the point along ω, the hemisphere's nodes gathered about the light's incoming direction."""
    m = points.shape[0]
    out = np.zeros(m)
    if m == 0 or src.sigma_s <= 0.0 or src.intensity <= 0.0:
        return out
    _, _, water, _, ok = _light(scene, src, points)
    to_src = np.where(ok[:, None], -np.nan_to_num(water), normals)
    k = 4 * fid.hemi_theta * fid.hemi_phi
    per = max(1, 200000 // k)
    for s in range(0, m, per):
        sl = slice(s, s + per)
        dirs, wd = hemisphere_directions(normals[sl], to_src[sl], fid.hemi_theta, fid.hemi_phi)
        dirs = dirs.reshape(-1, 3)
        orig = np.repeat(points[sl], dirs.shape[0] // points[sl].shape[0], axis=0)
        x0, x1 = box_interval(orig, dirs, src.box_lo, src.box_hi)
        res = line_stokes(scene, src, orig, dirs, x0, x1, fid.xi_nodes, np.zeros((1, 3)), np.zeros((1, 3)),
                          False)
        out[sl] = (res.b.reshape(points[sl].shape[0], -1) * wd).sum(1)
    view = src.sigma_t * segment_length_in_box(origins, points, src.box_lo, src.box_hi)
    return albedo / np.pi * np.exp(-view) * out


def _a_field(scene, src, fid, cam, view: PortView, pixels) -> np.ndarray:
    """A per pixel: exactly at requested pixels, else on a camera grid (A/ρ interpolated per object)."""
    hits, surf = view.hits, view.surf
    hit = np.nonzero(surf.object_id >= 0)[0]
    out = np.zeros(hits.t.size)

    def at(idx, origins, h, albedo):
        return port_surface_scatter(scene, src, origins[idx], h.point[idx], h.normal[idx], albedo, fid)

    if pixels is not None or fid.a_grid is None:
        out[hit] = at(hit, view.origins, hits, surf.albedo[hit])
        return out
    gw, gh = _CAMERA_GRID * fid.a_grid[0], _CAMERA_GRID * fid.a_grid[1]
    if src.pattern.kind == "stripe":
        gw, gh = 2 * gw, max(gh // 2, 2)
    gw, gh = min(gw, cam.w), min(gh, cam.h)
    GR, GC = np.meshgrid(np.linspace(0, cam.h - 1, gh), np.linspace(0, cam.w - 1, gw), indexing="ij")
    grid = port_view(scene, cam, np.stack([GR.ravel(), GC.ravel()], axis=1))
    gval = np.zeros(gh * gw)
    gidx = np.nonzero(grid.hits.index >= 0)[0]
    gval[gidx] = at(gidx, grid.origins, grid.hits, np.ones(gidx.size))
    return interpolate_grid(out, surf, cam, gval.reshape(gh, gw), grid.hits.index.reshape(gh, gw), {},
                            hit, lambda idx: at(idx, view.origins, hits, surf.albedo[idx]))


def port_parts(scene: Scene, src: Source, fid, cam: PinholeFrame, pixels, need, plan=None):
    """Flat (n,) D, A, B, Bq, Bu, Bv, Sq, Su through the ports (camera radiance through the camera's port:
    (n_a/n_w)² times its Mueller matrix on the water radiance, the object's light unpolarized in the water
    and polarized by the port, Sq, Su) and the surface info: single scattering, or all orders where ``plan``
    (an :class:`~polarstripe.sim.orders.OrdersPlan`) models them (:mod:`polarstripe.sim.port_higher`)."""
    if pixels is None:
        view = cached(scene, "port_camera", lambda: port_view(scene, cam, None))
    else:
        view = port_view(scene, cam, pixels)
    stokes = "p" in need or view.mueller is not None     # the port's B depends on B's polarization
    if plan is not None and plan.modelled:
        from polarstripe.sim.port_higher import port_higher

        need_w = tuple(need) + (("p",) if stokes and "p" not in need else ())
        D, A, B, Bq, Bu, Bv = port_higher(scene, src, plan, fid, cam, pixels, need_w, view)
    else:
        D, A, B, Bq, Bu, Bv = _single(scene, src, fid, cam, pixels, need, view, stokes)
    return _through_camera_port(view, need, D, A, B, Bq, Bu, Bv)


def _single(scene: Scene, src: Source, fid, cam: PinholeFrame, pixels, need, view: PortView, stokes: bool):
    """Single scattering's D, A, B, Bq, Bu, Bv (water radiance) along the camera's water rays."""
    n = view.dirs.shape[0]
    D, A, B, Bq, Bu, Bv = (np.zeros(n) for _ in range(6))
    hits, surf = view.hits, view.surf
    hit = np.nonzero(surf.object_id >= 0)[0]
    if "D" in need and hit.size:
        D[hit] = port_direct(scene, src, view.origins[hit], hits.point[hit], hits.normal[hit],
                             surf.albedo[hit])
    if "A" in need and hit.size and src.sigma_s > 0:
        A = _a_field(scene, src, fid, cam, view, pixels)
    if "B" in need and src.sigma_s > 0:
        t0, t1 = box_interval(view.origins, view.dirs, src.box_lo, src.box_hi)
        t1 = np.minimum(t1, hits.t)
        pol = stokes and scene.medium.dop.model == "rayleigh"
        res = line_stokes(scene, src, view.origins, view.dirs, t0, t1, fid.xi_nodes, view.cam_r, view.cam_u,
                          pol)
        B = res.b
        if pol:
            Bq, Bu, Bv = res.q, res.u, res.v
        elif stokes:
            Bq, Bu, Bv = camera_frame_stokes(src, scene, cam, view.dirs, B, None, None, None)
    return D, A, B, Bq, Bu, Bv


def _through_camera_port(view: PortView, need, D, A, B, Bq, Bu, Bv):
    """The camera radiance of water radiance: (n_a/n_w)² times the camera port's Mueller matrix (T where it
    is coated), and the surface info."""
    n, surf = view.dirs.shape[0], view.surf
    Sq, Su = np.zeros(n), np.zeros(n)
    if view.mueller is not None:
        m = view.mueller
        k = view.factor / (0.5 * (m.ts + m.tp))                      # (n_a/n_w)²
        B, Bq, Bu, Bv = (k * a for a in diattenuate(m.ts, m.tp, m.c2, m.s2, B, Bq, Bu, Bv))
        _, Sq, Su, _ = diattenuate(m.ts, m.tp, m.c2, m.s2, k * (D + A), 0.0, 0.0, 0.0)
        D, A = D * view.factor, A * view.factor
    else:
        D, A, B, Bq, Bu, Bv = (a * view.factor for a in (D, A, B, Bq, Bu, Bv))
    if "p" not in need:
        Bq, Bu, Bv, Sq, Su = (np.zeros(n) for _ in range(5))
    return D, A, B, Bq, Bu, Bv, Sq, Su, surf
