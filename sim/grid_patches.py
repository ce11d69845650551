"""The objects as sources of the higher-order grid (the glow, :mod:`polarstripe.sim.glow`): patches, light.

* :func:`object_patches` and :func:`glow_field` — objects as Lambertian sources: each patch of area A with
  exitance M sends beams of power M·A/N_d per unit length along N_d cosine-distributed directions; the
  pattern lights a patch by its lit fraction averaged over the patch (:func:`footprint_lit`), not at its
  centre, which would alias a checker finer than the patches.
* :func:`quasi_irradiance` — the quasi-direct light on surface points; :func:`patch_light` and
  :func:`patch_irradiance` — the same on the patches, its pattern-independent part kept for a scan's frames.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from polarstripe.sim.geometry import box_interval, intersect, occluded, projector_coords
from polarstripe.sim.grid_kernels import Beams, deposit_beams
from polarstripe.sim.grid_sources import fibonacci_sphere, lit_fraction
from polarstripe.sim.multiple import Field, Grid
from polarstripe.sim.patterns import pattern_lit
from polarstripe.sim.scene import BoxObject, PlaneObject, SphereObject
from polarstripe.sim.transport import Source


def footprint_lit(src: Source, points: np.ndarray, du: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """The pattern's lit fraction averaged over each patch p ± du/2 ± dv/2 (docs/physics.md §10.3): the
    rectangle in pattern pixels that bounds the projected corners, cut to the frame, through
    :func:`lit_fraction` (a patch wider than a checker square sees half of it lit, as the light it reflects
    does; a point sample would alias). 0 where the patch's centre is outside the frustum; the point's own
    value where a corner is behind the projector. Complementary patterns add up to the flood exactly."""
    inside, idx, rects = footprint_rects(src.frame, points, du, dv) if src.pattern.kind != "flood" else (
        _in_frustum(src.frame, points), None, None)
    out = np.zeros(points.shape[0])
    if src.pattern.kind == "flood" or not inside.any():
        return inside.astype(float)
    out[idx] = lit_fraction(src, *rects)
    return out


def _in_frustum(fr, points: np.ndarray) -> np.ndarray:
    col, row, depth = projector_coords(fr, points)
    return (depth > 0) & (row >= 0) & (row < fr.h) & (col >= 0) & (col < fr.w)


def footprint_rects(fr, points: np.ndarray, du: np.ndarray, dv: np.ndarray):
    """The pattern-independent part of :func:`footprint_lit` (the projector's frame ``fr``): which patches'
    centres are in the frustum, their indices and their rectangles (c0, c1, r0, r1) in pattern pixels."""
    col, row, depth = projector_coords(fr, points)
    inside = (depth > 0) & (row >= 0) & (row < fr.h) & (col >= 0) & (col < fr.w)
    idx = np.nonzero(inside)[0]
    corners = [points[idx] + a * du[idx] + b * dv[idx] for a in (-0.5, 0.5) for b in (-0.5, 0.5)]
    cc, rr, dd = projector_coords(fr, np.concatenate(corners))
    m = idx.size
    cc, rr, dd = cc.reshape(4, m), rr.reshape(4, m), dd.reshape(4, m)
    ahead = (dd > 0).all(axis=0)
    c0 = np.where(ahead, np.clip(cc.min(axis=0), 0.0, fr.w), col[idx])
    c1 = np.where(ahead, np.clip(cc.max(axis=0), 0.0, fr.w), col[idx])
    r0 = np.where(ahead, np.clip(rr.min(axis=0), 0.0, fr.h), row[idx])
    r1 = np.where(ahead, np.clip(rr.max(axis=0), 0.0, fr.h), row[idx])
    eps = 1e-6                                      # a patch seen edge-on: its centre's value
    c1, r1 = np.maximum(c1, c0 + eps), np.maximum(r1, r0 + eps)
    return inside, idx, (c0, c1, r0, r1)


class Patches(NamedTuple):
    """Surface patches: centres (m, 3), outward unit normals (m, 3), areas (m,) [m²], object index (m,), and
    the edges du, dv (m, 3) [m] of the parallelogram p ± du/2 ± dv/2 each stands for (a sphere's: a square of
    its area in the tangent plane)."""

    point: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    index: np.ndarray
    du: np.ndarray
    dv: np.ndarray


def _plane_patches(o: PlaneObject, lo, hi, spacing: float):
    from polarstripe.sim.geometry import plane_axes

    ra, ua = plane_axes(o)
    p0 = np.asarray(o.point, float)
    if o.size is None:
        c = 0.5 * (lo + hi)
        p0 = p0 + ra * ((c - p0) @ ra) + ua * ((c - p0) @ ua)
        w = h = float(np.linalg.norm(hi - lo))
    else:
        w, h = o.size
    nu, nv = max(2, int(math.ceil(w / spacing))), max(2, int(math.ceil(h / spacing)))
    u = ((np.arange(nu) + 0.5) / nu - 0.5) * w
    v = ((np.arange(nv) + 0.5) / nv - 0.5) * h
    U, V = np.meshgrid(u, v, indexing="ij")
    pts = p0 + U.ravel()[:, None] * ra + V.ravel()[:, None] * ua
    n = np.broadcast_to(np.asarray(o.normal, float), pts.shape)
    du, dv = np.broadcast_to(ra * (w / nu), pts.shape), np.broadcast_to(ua * (h / nv), pts.shape)
    return pts, n, np.full(pts.shape[0], w * h / (nu * nv)), du, dv


def _sphere_patches(o: SphereObject, spacing: float):
    r = o.radius
    n = int(np.clip(math.ceil(4 * math.pi * r * r / spacing ** 2), 16, 2000))
    d = fibonacci_sphere(n)
    area = 4 * math.pi * r * r / n
    helper = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(d, helper)
    e1 /= np.sqrt([v.dot(v) for v in e1])[:, None]        # as np.linalg.norm of each row, bit for bit
    side = math.sqrt(area)
    return np.asarray(o.center) + r * d, d, np.full(n, area), e1 * side, np.cross(d, e1) * side


def _box_patches(o: BoxObject, spacing: float):
    lo, hi = np.asarray(o.min, float), np.asarray(o.max, float)
    pts, nrm, area, eu, ev = [], [], [], [], []
    for ax in range(3):
        a, b = [k for k in range(3) if k != ax]
        na, nb = (max(1, int(math.ceil((hi[k] - lo[k]) / spacing))) for k in (a, b))
        ua = lo[a] + (np.arange(na) + 0.5) / na * (hi[a] - lo[a])
        ub = lo[b] + (np.arange(nb) + 0.5) / nb * (hi[b] - lo[b])
        A, B = np.meshgrid(ua, ub, indexing="ij")
        for side, val in ((-1.0, lo[ax]), (1.0, hi[ax])):
            p = np.zeros((A.size, 3))
            p[:, a], p[:, b], p[:, ax] = A.ravel(), B.ravel(), val
            nn = np.zeros_like(p)
            nn[:, ax] = side
            pts.append(p)
            nrm.append(nn)
            area.append(np.full(A.size, (hi[a] - lo[a]) * (hi[b] - lo[b]) / (na * nb)))
            e = np.zeros((2, A.size, 3))
            e[0, :, a], e[1, :, b] = (hi[a] - lo[a]) / na, (hi[b] - lo[b]) / nb
            eu.append(e[0])
            ev.append(e[1])
    return (np.concatenate(pts), np.concatenate(nrm), np.concatenate(area), np.concatenate(eu),
            np.concatenate(ev))


def object_patches(objects, lo, hi, spacing: float) -> Patches:
    """Patches about ``spacing`` [m] apart on every object, those inside the medium box only."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    parts = []
    for k, o in enumerate(objects):
        if isinstance(o, PlaneObject):
            p, n, a, du, dv = _plane_patches(o, lo, hi, spacing)
        elif isinstance(o, SphereObject):
            p, n, a, du, dv = _sphere_patches(o, spacing)
        else:
            p, n, a, du, dv = _box_patches(o, spacing)
        tol = 1e-9 + 1e-6 * float(np.abs(hi - lo).max())
        inside = np.all((p >= lo - tol) & (p <= hi + tol), axis=1)
        parts.append((p[inside], np.ascontiguousarray(n[inside]), a[inside], np.full(inside.sum(), k),
                      np.ascontiguousarray(du[inside]), np.ascontiguousarray(dv[inside])))
    if not parts:
        z = np.zeros((0, 3))
        return Patches(z, z, np.zeros(0), np.zeros(0, np.int64), z, z)
    return Patches(*(np.concatenate([q[i] for q in parts]) for i in range(6)))


def quasi_irradiance(src: Source, objects, points: np.ndarray, normals: np.ndarray,
                     lit_fraction: np.ndarray | None = None) -> np.ndarray:
    """Quasi-direct irradiance [W/m²] at surface points: I0·lit·cos·e^{−σ̃_t ℓ_LO}/(d² + r_s²), shadowed;
    lit is the pattern at each point, or ``lit_fraction`` where given (a patch's area average,
    :func:`footprint_lit`)."""
    from polarstripe.sim.geometry import segment_length_in_box

    v = src.position - points
    d2 = (v * v).sum(1)
    cos = np.clip((normals * v).sum(1) / np.sqrt(np.maximum(d2, 1e-300)), 0.0, None)
    # with the pattern's area average (lit_fraction) only the frame is checked here: the fraction weighs
    lit = pattern_lit(None if lit_fraction is not None else src.pattern, src.frame, points)
    if lit_fraction is not None and src.frame is not None:
        lit &= lit_fraction > 0
    if len(objects) and lit.any():
        idx = np.nonzero(lit)[0]
        lit[idx[occluded(objects, src.position, points[idx] + 1e-7 * normals[idx])]] = False
    ell = segment_length_in_box(src.position, points, src.box_lo, src.box_hi)
    weight = lit if lit_fraction is None or src.frame is None else np.where(lit, lit_fraction, 0.0)
    with np.errstate(under="ignore"):
        return np.where(lit, weight * src.intensity * cos * np.exp(-src.sigma_t * ell)
                        / np.maximum(d2 + src.radius ** 2, 1e-300), 0.0)


class PatchLight(NamedTuple):
    """The pattern-independent part of the quasi-direct irradiance of patches (kept per scene for a scan's
    frames): their footprints (:func:`footprint_rects`), which of them the source sees (centre in the
    frustum, not shadowed), cos, e^{−σ̃_t ℓ_LO} and max(d² + r_s², 1e-300)."""

    rects: tuple
    seen: np.ndarray
    cos: np.ndarray
    atten: np.ndarray
    denom: np.ndarray


def patch_light(src: Source, objects, points: np.ndarray, normals: np.ndarray, du: np.ndarray,
                dv: np.ndarray) -> PatchLight:
    """:class:`PatchLight` of the patches p ± du/2 ± dv/2 (a pinhole source): each term as
    :func:`quasi_irradiance` computes it, every patch in the frustum tested for shadow."""
    from polarstripe.sim.geometry import segment_length_in_box

    inside, idx, rects = footprint_rects(src.frame, points, du, dv)
    v = src.position - points
    d2 = (v * v).sum(1)
    cos = np.clip((normals * v).sum(1) / np.sqrt(np.maximum(d2, 1e-300)), 0.0, None)
    seen = inside.copy()
    if len(objects) and idx.size:
        seen[idx[occluded(objects, src.position, points[idx] + 1e-7 * normals[idx])]] = False
    ell = segment_length_in_box(src.position, points, src.box_lo, src.box_hi)
    with np.errstate(under="ignore"):
        atten = np.exp(-src.sigma_t * ell)
    return PatchLight((inside, idx, rects), seen, cos, atten, np.maximum(d2 + src.radius ** 2, 1e-300))


def patch_irradiance(src: Source, light: PatchLight) -> np.ndarray:
    """``quasi_irradiance(src, objects, points, normals, footprint_lit(src, points, du, dv))`` from the
    patches' :class:`PatchLight`, the same numbers: only the pattern's lit fractions are this frame's."""
    inside = light.rects[0]
    lit_frac = inside.astype(float) if src.pattern.kind == "flood" else np.zeros(inside.size)
    if src.pattern.kind != "flood" and inside.any():
        lit_frac[light.rects[1]] = lit_fraction(src, *light.rects[2])
    lit = light.seen & (lit_frac > 0)
    weight = np.where(lit, lit_frac, 0.0)
    return np.where(lit, weight * src.intensity * light.cos * light.atten / light.denom, 0.0)


def glow_beams(grid: Grid, patches: Patches, keep: np.ndarray, objects, directions: int = 32) -> Beams:
    """The beams of the patches ``keep`` of :func:`glow_field`, about ``directions`` each (a square number,
    cosine-weighted, a rotated stratification per patch), in the order of ``keep``, with the power of a
    unit exitance, area/k [W/m]."""
    k = int(max(4, directions))
    side = int(math.ceil(math.sqrt(k)))
    k = side * side
    u = (np.arange(side) + 0.5) / side
    U, V = (a.ravel() for a in np.meshgrid(u, u, indexing="ij"))
    rng = np.random.default_rng(12345)
    nrm = patches.normal[keep]
    helper = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(nrm, helper)
    e1 /= np.sqrt([v.dot(v) for v in e1])[:, None]        # as np.linalg.norm of each row, bit for bit
    e2 = np.cross(nrm, e1)
    rot = rng.uniform(0, 2 * math.pi, keep.size)      # a rotated stratification per patch: no ray stripes
    r, a = np.sqrt(U)[None, :], 2 * math.pi * V[None, :] + rot[:, None]
    dirs = ((r * np.cos(a))[..., None] * e1[:, None, :] + (r * np.sin(a))[..., None] * e2[:, None, :]
            + np.sqrt(1 - U)[None, :, None] * nrm[:, None, :]).reshape(-1, 3)
    orig = np.repeat(patches.point[keep] + 1e-7 * nrm, k, axis=0)
    t0, t1 = box_interval(orig, dirs, grid.lo, grid.hi)
    if len(objects):
        t1 = np.minimum(t1, intersect(objects, orig, dirs).t)
    return Beams(np.ascontiguousarray(orig), np.ascontiguousarray(dirs),
                 np.repeat(patches.area[keep] / k, k), t0, t1, np.zeros(t0.size))


def glow_field(grid: Grid, patches: Patches, exitance: np.ndarray, sigma: float, objects,
               directions: int = 32) -> Field:
    """First flight of the objects' reflected light: each patch a Lambertian source of exitance M [W/m²]."""
    phi, flux = np.zeros(grid.n), np.zeros((*grid.n, 3))
    keep = np.nonzero(exitance * patches.area > 0)[0]
    if keep.size == 0:
        return Field(phi, flux)
    beams = glow_beams(grid, patches, keep, objects, directions)
    k = beams.dirs.shape[0] // keep.size
    power = np.repeat(exitance[keep] * patches.area[keep] / k, k)
    deposit_beams(grid.args(), beams._replace(power=power), float(sigma), 0.5 * float(grid.h.min()), phi,
                  flux)
    return Field(phi, flux)
