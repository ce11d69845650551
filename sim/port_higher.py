"""All orders of scattering through flat ports (docs/physics.md §11): the split of docs/physics.md §10 with
the camera's water rays and the projector's refracted light.

* D: eq. 11 through the ports, exact (:func:`~polarstripe.sim.port_render.port_direct`, σ_t).
* Single wide-angle scattering: the port's line integrals (:mod:`~polarstripe.sim.port_kernels`) of the
  similarity-scaled source (σ̃_t, σ̃_s, P̃): B along the water rays, A's hemisphere rule at the objects (or,
  ``a1_exact`` off, the grid's once-scattered field, as :mod:`polarstripe.sim.higher` does).
* Orders ≥ 2 on the grid (:mod:`polarstripe.sim.multiple`): the source's beams are air rays through the lit
  pattern, each leaving the projector's port as its water ray with I0·ΔΩ_air·T
  (:func:`~polarstripe.sim.grid_sources.source_field`); B is their field's emission gathered along the
  camera's water rays (per-ray origins on the outer face), A its irradiance on the objects.
* The quasi-direct light on the objects (σ̃_t both ways) and its forward-cone blur
  (:func:`~polarstripe.sim.psf_frame.object_radiance`, whole frames), and the objects' glow
  (:func:`~polarstripe.sim.glow.glow_fields`, the patches lit through the projector's port).

Everything here is water radiance; :func:`~polarstripe.sim.port_render.port_parts` applies the camera's
T·(n_a/n_w)². Not carried through a port: the halo of a source in view (:func:`~polarstripe.sim.backscatter.
b_cone`) and, at requested pixels, the forward-cone blur (the object light is taken where it lands).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from polarstripe.sim.backscatter import (
    add_circular_orders,
    add_made_orders,
    add_polarized_orders,
    polarized_field,
    polarized_source,
    scaled_source,
)
from polarstripe.sim.frame_kernels import field_irradiance
from polarstripe.sim.geometry import box_interval, intersect, pixel_rays, segment_length_in_box
from polarstripe.sim.geometry_cache import cached
from polarstripe.sim.glow import glow_fields
from polarstripe.sim.grid_kernels import ViewArgs
from polarstripe.sim.grid_sources import (
    lit_fraction,
    port_source_gain,
    source_field,
    view_integral,
    view_table,
)
from polarstripe.sim.higher import object_light
from polarstripe.sim.multiple import Field, Grid, make_grid, solve_orders
from polarstripe.sim.orders import OrdersPlan
from polarstripe.sim.port import PortGeometry, light_to, port_geometry, water_rays
from polarstripe.sim.surface_field import View, camera_frame_stokes
from polarstripe.sim.threads import in_bands
from polarstripe.sim.transport import Source


def projector_port(scene, src: Source) -> PortGeometry | None:
    """The projector's port placed in the world (None: it has none)."""
    pr = scene.projector
    if pr.port is None:
        return None
    forward = src.frame.f if src.frame is not None else np.subtract(pr.look_at, pr.position)
    return port_geometry(pr.port, pr.position, forward)


def camera_port_rays(scene, cam):
    """``rays_of(pixels)`` → (origins, directions) of the camera's water rays (None: no camera port)."""
    if scene.camera.port is None:
        return None
    geo = port_geometry(scene.camera.port, cam.position, cam.f)

    def rays_of(pixels):
        origins, dirs, _, _ = water_rays(geo, pixel_rays(cam, pixels))
        return origins, dirs

    return rays_of


def _pattern_coords(fr, air: np.ndarray):
    """Pattern (col, row, depth) of air directions from the projector's pinhole."""
    depth = air @ fr.f
    with np.errstate(divide="ignore", invalid="ignore"):
        return fr.w / 2.0 + (air @ fr.r) / depth / fr.s, fr.h / 2.0 - (air @ fr.u) / depth / fr.s, depth


def port_light(scene, ssrc: Source, port: PortGeometry, pts: np.ndarray, nrm: np.ndarray, du=None,
               dv=None) -> np.ndarray:
    """Quasi-direct irradiance [W/m²] at surface points lit through the projector's port: I0·T·J·lit·cos·
    e^{−σ̃_t ℓ} (ℓ from the exit point on the outer face), shadowed; lit the pattern at each point, or, for
    patches p ± du/2 ± dv/2, its fraction over the rectangle of pattern pixels that bounds the corners' air
    rays (as :func:`~polarstripe.sim.grid_patches.footprint_lit` does without a port)."""
    m = pts.shape[0]
    if du is None:
        du = dv = np.zeros_like(pts)
    out = np.zeros(m)
    if m == 0 or ssrc.intensity <= 0.0:
        return out
    lt = light_to(port, pts)
    lit = lt.ok.astype(float)
    fr = ssrc.frame
    if fr is not None:
        col, row, depth = _pattern_coords(fr, np.nan_to_num(lt.air))
        inside = lt.ok & (depth > 0) & (row >= 0) & (row < fr.h) & (col >= 0) & (col < fr.w)
        lit = np.zeros(m)
        idx = np.nonzero(inside)[0]
        if ssrc.pattern.kind == "flood":
            lit[idx] = 1.0
        elif idx.size:
            corners = np.concatenate([pts[idx] + a * du[idx] + b * dv[idx]
                                      for a in (-0.5, 0.5) for b in (-0.5, 0.5)])
            lc = light_to(port, corners)
            coords = _pattern_coords(fr, np.nan_to_num(lc.air))
            cc, rr, dd = (np.asarray(x).reshape(4, idx.size) for x in coords)
            good = lc.ok.reshape(4, idx.size).all(axis=0) & (dd > 0).all(axis=0)
            c0 = np.where(good, np.clip(cc.min(axis=0), 0.0, fr.w), col[idx])
            c1 = np.where(good, np.clip(cc.max(axis=0), 0.0, fr.w), col[idx])
            r0 = np.where(good, np.clip(rr.min(axis=0), 0.0, fr.h), row[idx])
            r1 = np.where(good, np.clip(rr.max(axis=0), 0.0, fr.h), row[idx])
            eps = 1e-6                                 # a patch seen edge-on: its centre's value
            lit[idx] = lit_fraction(ssrc, c0, np.maximum(c1, c0 + eps), r0, np.maximum(r1, r0 + eps))
    idx = np.nonzero(lit > 0)[0]
    if idx.size == 0:
        return out
    start = lt.exit[idx]
    v = pts[idx] + 1e-7 * nrm[idx] - start
    dist = np.linalg.norm(v, axis=1)
    hits = intersect(scene.objects, np.ascontiguousarray(start), v / np.maximum(dist, 1e-300)[:, None])
    idx = idx[~(hits.t < dist * (1.0 - 1e-9) - 1e-9)]
    cos = np.clip(-np.einsum("ij,ij->i", nrm[idx], lt.water[idx]), 0.0, None)
    ell = segment_length_in_box(lt.exit[idx], pts[idx], ssrc.box_lo, ssrc.box_hi)
    gain = port_source_gain(port, ssrc, np.nan_to_num(lt.air[idx]))
    out[idx] = ssrc.intensity * lt.J[idx] * lt.T[idx] * gain * lit[idx] * cos * np.exp(-ssrc.sigma_t * ell)
    return out


def _irradiance(grid: Grid, field: Field, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    out, args = np.empty(points.shape[0]), grid.args()
    points, normals = np.ascontiguousarray(points), np.ascontiguousarray(normals)
    in_bands(out.size, lambda a, b: field_irradiance(args, field.phi, field.flux, points[a:b], normals[a:b],
                                                     out[a:b]))
    return out


def _b_stokes(scene, src: Source, ssrc: Source, psrc, cam, view, fid, need, seen, lin, circ):
    """B, Bq, Bu, Bv: single wide-angle scattering along the water rays plus the grid's orders ≥ 2."""
    from polarstripe.sim.port_render import line_stokes

    hits = view.hits
    t0, t1 = box_interval(view.origins, view.dirs, ssrc.box_lo, ssrc.box_hi)
    t1 = np.minimum(t1, hits.t)
    dop = scene.medium.dop
    pol = psrc is not None
    one = line_stokes(scene, psrc if pol else ssrc, view.origins, view.dirs, t0, t1, fid.xi_nodes, view.cam_r,
                      view.cam_u, pol)           # psrc: the Stokes sums with σ_p (docs/physics.md §10.4)
    n = view.dirs.shape[0]
    B, Bq, Bu, Bv = one.b.copy(), np.zeros(n), np.zeros(n), np.zeros(n)
    if pol:
        Bq, Bu, Bv = one.q.copy(), one.u.copy(), one.v.copy()
        single = (B.copy(), Bq.copy(), Bu.copy())
        delta, k = float(dop.depolarization), 1
        if lin != 0.0:
            Bq, Bu = add_polarized_orders(Bq, Bu, seen[k], (1.0 - delta) * abs(lin))
            k += 1
        if circ != 0.0:
            Bv = add_circular_orders(Bv, seen[k], -(1.0 - 2.0 * delta) * circ)
        if abs(lin) < 1.0:
            Bq, Bu = add_made_orders(Bq, Bu, *single, seen[0], 1.0 - abs(lin))
    B += seen[0]
    if "p" in need and not pol:
        Bq, Bu, Bv = camera_frame_stokes(src, scene, cam, view.dirs, B, None, None, None)
    return B, Bq, Bu, Bv


def port_higher(scene, src: Source, plan: OrdersPlan, fid, cam, pixels, need, view):
    """D, A, B, Bq, Bu, Bv (flat, water radiance) with all orders through the ports (module docstring);
    ``view`` the camera's :class:`~polarstripe.sim.port_render.PortView`."""
    from polarstripe.sim.port_render import _a_field as a_field  # the port's A1 hemisphere rule
    from polarstripe.sim.port_render import port_direct

    st, sc = fid.higher, plan.scaled
    ssrc = scaled_source(src, plan)
    hits, surf = view.hits, view.surf
    n = view.dirs.shape[0]
    hit = surf.object_id >= 0
    idx = np.nonzero(hit)[0]
    zeros = (np.zeros(n) for _ in range(6))
    D, A, B, Bq, Bu, Bv = zeros
    want_a = "A" in need and idx.size > 0
    if ("D" in need or want_a) and idx.size:
        D[idx] = port_direct(scene, src, view.origins[idx], hits.point[idx], hits.normal[idx],
                             surf.albedo[idx])
    if not (want_a or "B" in need) or sc.sigma_s <= 0:
        return (D if "D" in need else np.zeros(n)), A, B, Bq, Bu, Bv
    port = projector_port(scene, src)
    grid = make_grid(ssrc.box_lo, ssrc.box_hi, st.cells)
    orders = solve_orders(grid, source_field(grid, ssrc, scene.objects, st.oversample, port), sc.sigma_t,
                          sc.sigma_s, sc.g_tilde, orders=st.orders)
    pview = View(scene, src.pattern, fid, cam, view.dirs, hits, surf, pixels)
    fields = [orders.total] if "B" in need else []
    sigmas = [sc.sigma_t] * len(fields)
    dop = scene.medium.dop
    lin, circ = src.linear_circular
    psrc = None
    if "p" in need and "B" in need and dop.model == "rayleigh":
        psrc = polarized_source(src, plan, scene)
        for on, circular, sigma in ((lin != 0.0, False, psrc.sigma_pol),
                                    (circ != 0.0, True, psrc.sigma_pol_v)):
            if on:
                fields.append(polarized_field(psrc, plan, scene, st, grid, circular, port))
                sigmas.append(sigma)
    glow_scattered = None
    if want_a:
        def light(p):
            return port_light(scene, ssrc, port, p.point, p.normal, p.du, p.dv)

        seen_glow, glow_scattered = glow_fields(pview, ssrc, plan, st, grid, orders.total,
                                                None if port is None else light)
        fields.append(seen_glow)
        sigmas.append(sc.sigma_t)
    rays_of = camera_port_rays(scene, cam)
    _, t1g = box_interval(view.origins, view.dirs, grid.lo, grid.hi)
    x_end = np.minimum(t1g, hits.t)
    args = ViewArgs(np.full(len(fields), sc.sigma_s / (4 * np.pi)), np.full(len(fields), sc.g_tilde),
                    np.array(sigmas, float), np.zeros((1, 3)))
    coarse = (min(cam.w, max(cam.w // st.view_div, 16)), min(cam.h, max(cam.h // st.view_div, 12)))
    table = None if pixels is not None else cached(
        scene, ("port_view_table", cam.w, cam.h, grid, coarse, st.view_steps),
        lambda: view_table(grid, cam, x_end, coarse, st.view_steps, rays_of))
    seen = view_integral(grid, fields, args, cam, pixels, x_end, coarse, st.view_steps, table, rays_of)
    if "B" in need:
        B, Bq, Bu, Bv = _b_stokes(scene, src, ssrc, psrc, cam, view, fid, need, seen, lin, circ)
    if want_a:
        A = _object_light(scene, src, ssrc, plan, fid, cam, pixels, view, pview, grid, orders, glow_scattered,
                          D, port, a_field)
        A += seen[-1]
    return (D if "D" in need else np.zeros(n)), A, B, Bq, Bu, Bv


def _object_light(scene, src, ssrc, plan, fid, cam, pixels, view, pview, grid, orders, glow_scattered, D,
                  port, a_field):
    """A beyond D and the glow: the quasi-direct light, single wide-angle scattering and the grid's
    irradiance on the objects, after the forward cone's blurs (module docstring)."""
    from polarstripe.sim.port_render import port_direct

    st, sc = fid.higher, plan.scaled
    hits, surf = view.hits, view.surf
    n = view.dirs.shape[0]
    hit = surf.object_id >= 0
    idx = np.nonzero(hit)[0]
    pts, nrm = hits.point[idx], hits.normal[idx]
    quasi, rest = np.zeros(n), np.zeros(n)
    quasi[idx] = port_direct(scene, ssrc, view.origins[idx], pts, nrm, np.ones(idx.size))   # per unit albedo
    if st.a1_exact:
        unit = view._replace(surf=dataclasses.replace(surf, albedo=np.ones(n)))
        rest = a_field(scene, ssrc, fid, cam, unit, pixels)
        e2 = _irradiance(grid, orders.total - orders.first + glow_scattered, pts, nrm)
    else:
        e2 = _irradiance(grid, orders.total + glow_scattered, pts, nrm)
    lo, hi = np.asarray(ssrc.box_lo, float), np.asarray(ssrc.box_hi, float)
    ell_c, ell_l = np.zeros(n), np.zeros(n)
    ell_c[idx] = segment_length_in_box(view.origins[idx], pts, lo, hi)
    start = np.asarray(src.position, float) if port is None else np.nan_to_num(light_to(port, pts).exit)
    ell_l[idx] = segment_length_in_box(start, pts, lo, hi)
    rest[idx] += np.maximum(e2, 0.0) * np.exp(-sc.sigma_t * ell_c[idx]) / np.pi
    port_c = scene.camera.port         # the halo's pixel scale: the water's angular pitch, paraxially
    blur_cam = cam if port_c is None else dataclasses.replace(cam, s=cam.s * port_c.n_air / port_c.n_water)
    light = None if port is None else (lambda p, q: port_light(scene, ssrc, port, p, q))
    out = object_light(pview._replace(cam=blur_cam), ssrc, plan, quasi, rest, (ell_l, ell_c),
                       camera_port_rays(scene, cam), light)
    if pixels is not None:
        return np.maximum(out - D, 0.0)
    return surf.albedo * out[0] + out[1]
