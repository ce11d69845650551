"""The surface term A of whole frames and the backscatter's camera-frame Stokes (moved out of
:mod:`polarstripe.sim.render`; the single-scattering and the higher-order renders share them).

:func:`a_field` evaluates A per pixel: exactly at requested pixels, else on a coarse grid (a plane's pattern
coordinates, or the camera image) and interpolated per object (docs/physics.md §2.4).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
from polarstripe.sim.geometry import box_interval, intersect, occluded, pixel_rays
from polarstripe.sim.kernel_records import Stokes
from polarstripe.sim.kernels import camera_stokes
from polarstripe.sim.patterns import PatternSpec, lit_intervals, pattern_lit, single_sheets, stripe_columns
from polarstripe.sim.scene import PlaneObject, Scene
from polarstripe.sim.surface import SurfaceInfo
from polarstripe.sim.surface_grid import plane_stripe_field
from polarstripe.sim.surface_term import surface_scatter_beams
from polarstripe.sim.transport import Source, direct, line_radiance, surface_scatter

_CAMERA_GRID = 3      # objects other than planes: an A grid of a_grid × this over the image


class View(NamedTuple):
    """One render's camera side: scene, pattern, Fidelity, camera PinholeFrame, ray directions (n, 3), their
    Hits, SurfaceInfo, and the requested pixels (None: the whole image)."""

    scene: Scene
    pattern: PatternSpec
    fid: object
    cam: object
    dirs: np.ndarray
    hits: object
    surf: SurfaceInfo
    pixels: np.ndarray | None


def single_parts(view: View, src: Source, need) -> tuple[np.ndarray, ...]:
    """Single scattering (paper eqs. 11–13, physical form) of ``src``: flat (n,) D, A, B, Bq, Bu, Bv per
    ray."""
    scene, pat, fid, cam, dirs, hits, surf, pixels = view
    n = dirs.shape[0]
    D, A, B, Bq, Bu, Bv = (np.zeros(n) for _ in range(6))
    hit = np.nonzero(surf.object_id >= 0)[0] if "D" in need or "A" in need else None
    if "D" in need and hit.size:
        lit_idx = hit[pattern_lit(pat, src.frame, hits.point[hit])]          # shadow rays only where lit
        lit_idx = lit_idx[~occluded(scene.objects, src.position, hits.point[lit_idx])]
        pts = hits.point[lit_idx]
        D[lit_idx] = direct(src, scene.objects, cam.position, pts, hits.normal[lit_idx], surf.albedo[lit_idx],
                            np.ones(lit_idx.size, bool))
    if "A" in need and hit.size and src.sigma_s > 0:
        A = a_field(src, scene, fid, cam, hits, surf, pixels)
    if "B" in need and src.sigma_s > 0:
        t0, t1 = box_interval(cam.position, dirs, src.box_lo, src.box_hi)
        t1 = np.minimum(t1, hits.t)
        lit = lit_intervals(pat, src.frame, cam.position, dirs, t0, t1)
        pol = "p" in need and scene.medium.dop.model == "rayleigh"
        res = line_radiance(src, cam.position, dirs, t0, lit, fid.xi_nodes, polarization=pol)
        B, q, u, v = res if pol else (res, None, None, None)
        if "p" in need:
            Bq, Bu, Bv = camera_frame_stokes(src, scene, cam, dirs, B, q, u, v)
    return D, A, B, Bq, Bu, Bv


def a_field(src: Source, scene: Scene, fid, cam, hits, surf: SurfaceInfo, pixels) -> np.ndarray:
    """A per pixel: directly at requested pixels, else on the coarse grid and interpolated per object. A of
    several sheets is the sum of each sheet's (A is linear in the lit light; each sheet's edges keep the
    one-sheet rules and grid)."""
    if len(sheets := single_sheets(src.pattern)) > 1:
        return sum(a_field(dataclasses.replace(src, pattern=one), scene, fid, cam, hits, surf, pixels)
                   for one in sheets)
    n = hits.t.size
    a_out = np.zeros(n)
    hit = surf.object_id >= 0
    cpos = np.asarray(scene.camera.position)

    beams = fid.a_side > 0 and src.frame is not None and src.pattern.kind in ("flood", "stripe")

    def a_at(points, normals, albedo):
        if beams:
            return surface_scatter_beams(src, scene.objects, cpos, points, normals, albedo, fid.xi_nodes,
                                         fid.a_side)
        return surface_scatter(src, cpos, points, normals, albedo, fid.xi_nodes, fid.hemi_theta, fid.hemi_phi)

    def at(idx):
        return a_at(hits.point[idx], hits.normal[idx], surf.albedo[idx])

    if pixels is not None or fid.a_grid is None:
        idx = np.nonzero(hit)[0]
        a_out[idx] = at(idx)
        return a_out
    gw, gh = fid.a_grid
    done = np.zeros(n, bool)
    if src.pattern.kind in ("stripe", "flood") and src.frame is not None:   # planes: pattern coordinates
        c0, c1 = (0, src.frame.w) if src.pattern.kind == "flood" else stripe_columns(src.pattern, src.frame.w)
        for k in np.unique(surf.object_id[hit]):
            if not isinstance(scene.objects[k], PlaneObject):
                continue
            idx = np.nonzero(surf.object_id == k)[0]
            val = plane_stripe_field(src.frame, scene.objects[k], hits.point[idx], c0, c1, gw, gh, a_at)
            if val is not None:
                a_out[idx] = surf.albedo[idx] * val
                done[idx] = True
        if done[hit].all():
            return a_out
    gw, gh = _CAMERA_GRID * gw, _CAMERA_GRID * gh     # other objects: a grid over the image
    if src.pattern.kind == "stripe":
        gw, gh = 2 * gw, max(gh // 2, 2)             # A of a stripe varies fast across it, slowly along it
    gw, gh = min(gw, cam.w), min(gh, cam.h)
    gr = np.linspace(0, cam.h - 1, gh)
    gc = np.linspace(0, cam.w - 1, gw)
    GR, GC = np.meshgrid(gr, gc, indexing="ij")
    gdirs = pixel_rays(cam, np.stack([GR.ravel(), GC.ravel()], axis=1))
    ghits = intersect(scene.objects, cam.position, gdirs)
    gval = np.zeros(gdirs.shape[0])
    gidx = np.nonzero(ghits.index >= 0)[0]
    # A/ρ is smooth across texture edges: interpolate the albedo-free part, multiply by the pixel's albedo
    gval[gidx] = a_at(ghits.point[gidx], ghits.normal[gidx], np.ones(gidx.size))
    gval, gobj = gval.reshape(gh, gw), ghits.index.reshape(gh, gw)
    fields = extend_planes(scene, cam, gdirs, gval, gobj, a_at)
    return interpolate_grid(a_out, surf, cam, gval, gobj, fields, np.nonzero(hit & ~done)[0], at)


def interpolate_grid(a_out, surf: SurfaceInfo, cam, gval, gobj, fields: dict, idx, exact) -> np.ndarray:
    """Fill ``a_out`` at pixels ``idx`` from the (gh, gw) grid of A/ρ ``gval`` over the image (object index
    per node ``gobj``; ``fields``: per object (values, valid) replacing them) by bilinear interpolation over
    the nodes on the pixel's own object, times the pixel's albedo; ``exact(idx)`` where none is near."""
    gh, gw = gval.shape
    rows, cols = idx // cam.w, idx % cam.w
    fr = rows * (gh - 1) / max(cam.h - 1, 1)
    fc = cols * (gw - 1) / max(cam.w - 1, 1)
    r0 = np.clip(np.floor(fr).astype(int), 0, max(gh - 2, 0))
    c0 = np.clip(np.floor(fc).astype(int), 0, max(gw - 2, 0))
    tr, tc = fr - r0, fc - c0
    num = np.zeros(idx.size)
    den = np.zeros(idx.size)
    obj = surf.object_id[idx]
    for k in np.unique(obj):
        sel = obj == k
        vals, valid = fields.get(int(k), (gval, gobj == k))
        for dr, wr in ((0, 1 - tr[sel]), (1, tr[sel])):
            for dc, wc in ((0, 1 - tc[sel]), (1, tc[sel])):
                rr, cc = np.minimum(r0[sel] + dr, gh - 1), np.minimum(c0[sel] + dc, gw - 1)
                wgt = wr * wc * valid[rr, cc]
                num[sel] += wgt * vals[rr, cc]
                den[sel] += wgt
    good = den > 1e-6
    a_out[idx[good]] = surf.albedo[idx[good]] * num[good] / den[good]
    miss = idx[~good]
    if miss.size:
        a_out[miss] = exact(miss)
    return a_out


def extend_planes(scene: Scene, cam, gdirs, gval, gobj, a_at) -> dict:
    """Per plane object: its A/ρ grid extended by one ring of nodes on the plane's continuation, so pixels at
    the plane's edge interpolate instead of extrapolating. Returns {object index: (values, valid)}."""
    gh, gw = gobj.shape
    out = {}
    for k, o in enumerate(scene.objects):
        mine = gobj == k
        if not isinstance(o, PlaneObject) or not mine.any():
            continue
        pad = np.pad(mine, 1)
        ring = np.zeros_like(mine)
        for dr in (0, 1, 2):
            for dc in (0, 1, 2):
                ring |= pad[dr:dr + gh, dc:dc + gw]
        ring &= ~mine
        where = np.nonzero(ring.ravel())[0]
        n = np.asarray(o.normal)
        d = gdirs[where]
        dn = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((np.asarray(o.point) - cam.position) @ n) / dn
        ok = (dn < 0) & (t > 0)
        where, t, d = where[ok], t[ok], d[ok]
        vals = np.where(mine, gval, 0.0).ravel()
        valid = mine.ravel().copy()
        if where.size:
            pts = cam.position + t[:, None] * d
            vals[where] = a_at(pts, np.broadcast_to(n, pts.shape), np.ones(where.size))
            valid[where] = True
        out[k] = (vals.reshape(gh, gw), valid.reshape(gh, gw))
    return out


def camera_frame_stokes(src: Source, scene: Scene, cam, dirs, B, q, u, v=None):
    """Rotate the per-ray (q, u) sums from the scattering-plane frame into the camera frame (r, u axes); v
    (circular) needs no rotation: (e_par, e_perp, k) and (r, u, −f) are both right-handed about the light's
    direction (docs/physics.md §5.1). ``dop.model = "constant"``: p times the source's state along its
    axis, the helicity flipped (a mirror-like backscatter)."""
    dop = scene.medium.dop
    if dop.model == "constant":
        axis = src.fast_axis if np.any(src.fast_axis) else src.e_field
        chi = np.arctan2(axis @ cam.u, axis @ cam.r)
        lin, circ = src.linear_circular
        return B * dop.p * lin * np.cos(2 * chi), B * dop.p * lin * np.sin(2 * chi), -B * dop.p * circ
    qc, uc = np.empty_like(B), np.empty_like(B)
    camera_stokes(np.asarray(src.position, float), np.asarray(cam.position, float),
                  np.ascontiguousarray(dirs), cam.r, cam.u, Stokes(B, q, u, np.zeros(1)), qc, uc)
    return qc, uc, (np.zeros_like(B) if v is None else v)


