"""What feeds the higher-order grid and what is read back from it (:mod:`polarstripe.sim.multiple`).

* :func:`source_field` — the quasi-direct light of the projector (or point source) as fluence and flux per
  cell: beams from the source through the lit pattern, each carrying I0·ΔΩ·e^{−σ̃_t s} per unit length
  (dV = s² ds dΩ cancels the 1/s² of the point source, so a cell receives exactly the power that crosses it),
  ending at the first object. A beam's weight is its solid angle times the lit fraction of its patch of
  pattern pixels, so the lit power is exact for stripes and checkers finer than the grid.
* :func:`object_patches` and :func:`glow_field` — objects as Lambertian sources: each patch of area A with
  exitance M sends beams of power M·A/N_d per unit length along N_d cosine-distributed directions; the
  pattern lights a patch by its lit fraction averaged over the patch (:func:`footprint_lit`), not at its
  centre, which would alias a checker finer than the patches.
* :func:`view_integral` — the in-scattered radiance J(Y, −d) = c(φ + 3g̃F·(−d)) integrated along the view
  rays with the view's attenuation, on a coarse set of rays with per-pixel depths.
* :func:`surface_irradiance` — the P1 irradiance E = φ/4 − F·n/2 onto a surface of outward normal n.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from polarstripe.sim.frame_kernels import view_depths, view_gather
from polarstripe.sim.geometry import box_interval, intersect, occluded, pixel_rays, projector_coords
from polarstripe.sim.grid_kernels import (
    Beams,
    ViewArgs,
    deposit_beams,
    sample_fields,
    view_cumulative,
    view_lookup,
)
from polarstripe.sim.multiple import Field, Grid
from polarstripe.sim.patterns import gray_lit, pattern_lit, sheet_columns
from polarstripe.sim.port import water_rays
from polarstripe.sim.port_kernels import source_port_gain
from polarstripe.sim.scene import BoxObject, PlaneObject, SphereObject
from polarstripe.sim.threads import in_bands
from polarstripe.sim.transport import Source

_MAX_BEAMS = 60000


def _fibonacci(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    r = np.sqrt(np.maximum(1 - z * z, 0.0))
    a = math.pi * (1 + 5 ** 0.5) * k
    return np.stack([r * np.cos(a), r * np.sin(a), z], 1)


def _square_mean(a: np.ndarray, b: np.ndarray, size: float) -> np.ndarray:
    """Mean over [a, b] of the square wave q(x) = +1 where floor(x/size) is even, −1 where odd: its integral
    is the triangle wave T(x) = y for y = x mod 2·size < size, else 2·size − y, so the mean is
    (T(b) − T(a))/(b − a) (q(a) itself for an empty interval)."""
    def tri(x):
        y = np.mod(x, 2.0 * size)
        return np.where(y < size, y, 2.0 * size - y)

    w = b - a
    point = np.where(np.floor(a / size) % 2 == 0, 1.0, -1.0)
    wide = w > 1e-9 * size
    return np.where(wide, (tri(b) - tri(a)) / np.where(wide, w, 1.0), point)


def lit_fraction(src: Source, c0: np.ndarray, c1: np.ndarray, r0: np.ndarray, r1: np.ndarray) -> np.ndarray:
    """Lit fraction of each rectangle [c0, c1] × [r0, r1] of pattern pixels: exact for flood, stripes and
    checkers (lit = (1 + q(col − shift)·q(row))/2 with q the square wave of :func:`_square_mean`, separable
    over a rectangle; several sheets: the sum of theirs), 4 × 4 sub-samples for Gray code."""
    pat = src.pattern
    if pat.kind == "flood":
        return np.ones(c0.shape)
    if pat.kind == "stripe":       # the sheets are disjoint: their lit fractions add
        return sum(np.clip(np.minimum(c1, s1) - np.maximum(c0, s0), 0.0, None)
                   for s0, s1 in sheet_columns(pat, src.frame.w)) / (c1 - c0)
    if pat.kind == "gray":
        u = (np.arange(4) + 0.5) / 4
        col = c0[:, None, None] + (c1 - c0)[:, None, None] * u[None, :, None]
        row = r0[:, None, None] + (r1 - r0)[:, None, None] * u[None, None, :]
        return gray_lit(pat, col, row).mean(axis=(1, 2))
    size, shift = float(pat.size), float(pat.shift % (2 * pat.size))
    return 0.5 + 0.5 * _square_mean(c0 - shift, c1 - shift, size) * _square_mean(r0, r1, size)


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


class SourceBeams(NamedTuple):
    """The source's beams through its whole frustum, whatever the pattern (the same for every frame of a
    scan): directions (m, 3), power per unit length I0·ΔΩ [W/m] before the pattern, each beam's rectangle
    of pattern pixels (c0, c1, r0, r1) (None: a point source, lit everywhere), and where each beam enters
    the grid's box and ends (t0, t1: the box's far side or the first object; None until
    :func:`source_beams` fills them)."""

    dirs: np.ndarray
    power: np.ndarray
    rects: tuple | None
    t0: np.ndarray | None = None
    t1: np.ndarray | None = None


def _source_beams(src: Source, grid: Grid, oversample: float) -> SourceBeams:
    """Beam directions and their power per unit length before the pattern (:class:`SourceBeams`)."""
    corners = np.array([[x, y, z] for x in (grid.lo[0], grid.hi[0]) for y in (grid.lo[1], grid.hi[1])
                        for z in (grid.lo[2], grid.hi[2])])
    far = float(np.linalg.norm(corners - src.position, axis=1).max())
    step = float(grid.h.min()) / (2.0 * oversample * max(far, 1e-9))   # beam spacing [rad], far side
    if src.frame is None:
        m = int(min(max(4 * math.pi / step ** 2, 256), _MAX_BEAMS))
        return SourceBeams(_fibonacci(m), np.full(m, src.intensity * 4 * math.pi / m), None)
    fr = src.frame
    c_lo, c_hi = 0.0, float(fr.w)        # the whole frustum whatever the pattern: stripes add up to the flood
    nc = int(np.clip(math.ceil((c_hi - c_lo) * fr.s / step), 1, 400))
    nr = int(np.clip(math.ceil(fr.h * fr.s / step), 1, 400))
    while nc * nr > _MAX_BEAMS:
        nc, nr = max(1, nc // 2), max(1, nr // 2)
    ce = np.linspace(c_lo, c_hi, nc + 1)
    re = np.linspace(0.0, float(fr.h), nr + 1)
    C0, R0 = np.meshgrid(ce[:-1], re[:-1], indexing="ij")
    C1, R1 = np.meshgrid(ce[1:], re[1:], indexing="ij")
    c0, c1, r0, r1 = C0.ravel(), C1.ravel(), R0.ravel(), R1.ravel()
    cm, rm = 0.5 * (c0 + c1), 0.5 * (r0 + r1)
    a, b = (cm - fr.w / 2) * fr.s, (rm - fr.h / 2) * fr.s
    dirs = fr.f[None, :] + a[:, None] * fr.r - b[:, None] * fr.u
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    solid = (c1 - c0) * (r1 - r0) * fr.s * fr.s * (1 + a * a + b * b) ** -1.5
    return SourceBeams(dirs, src.intensity * solid, (c0, c1, r0, r1))


def source_beams(grid: Grid, src: Source, objects, oversample: float = 1.0) -> SourceBeams:
    """The beams of :func:`source_field` with their ends in the box (no port): what a scan's frames share
    (the pattern only weights them; each beam's ends are computed as :func:`source_field` computes them)."""
    beams = _source_beams(src, grid, oversample)
    origin = np.asarray(src.position, float)
    t0, t1 = box_interval(origin, beams.dirs, grid.lo, grid.hi)
    if len(objects):
        t1 = np.minimum(t1, intersect(objects, origin, beams.dirs).t)
    return beams._replace(t0=t0, t1=t1)


def port_source_gain(port, src: Source, air: np.ndarray) -> np.ndarray:
    """i'/T of the source's light through its ``port`` along the air rays ``air`` (n, 3): the port's Mueller
    matrix's intensity for the source's polarization (1: unpolarized, or a coated port; docs/physics.md
    §11)."""
    gain = np.ones(air.shape[0])
    if port.fresnel and src.dop_l > 0.0:
        source_port_gain(np.ascontiguousarray(air, float), port.normal, port.t, port.n_a, port.n_g, port.n_w,
                         np.asarray(src.e_field, float), np.asarray(src.fast_axis, float),
                         bool(np.any(src.fast_axis)), float(src.dop_l), gain)
    return gain


def source_field(grid: Grid, src: Source, objects, oversample: float = 1.0, port=None,
                 beams: SourceBeams | None = None) -> Field:
    """The quasi-direct light's fluence φ₀ and flux F₀ per cell (module docstring); ``src`` is the scaled
    source (σ̃_t). ``oversample`` multiplies the beam density (1: beams half a cell apart at the far side).
    ``port`` (a :class:`~polarstripe.sim.port.PortGeometry`): the source looks through a flat port; each air
    beam becomes its water ray (from the outer face, refracted) carrying I0·ΔΩ_air·T, T the port's
    transmittance for the source's polarization (:func:`port_source_gain`; docs/physics.md §11). ``beams``:
    :func:`source_beams` of this grid, source pose and objects (no port), kept for a scan's frames."""
    phi, flux = np.zeros(grid.n), np.zeros((*grid.n, 3))
    if src.intensity <= 0.0:
        return Field(phi, flux)
    if beams is None:
        beams = _source_beams(src, grid, oversample)
    power = beams.power if beams.rects is None else beams.power * lit_fraction(src, *beams.rects)
    keep = power > 0
    dirs, origin = beams.dirs, np.asarray(src.position, float).reshape(1, 3)
    if port is not None:          # only the air rays that leave through the window's side
        keep &= dirs @ port.normal > 1e-9
    dirs, power = np.ascontiguousarray(dirs[keep]), power[keep]
    if port is not None:
        gain = port_source_gain(port, src, dirs)
        origin, dirs, trans, _ = water_rays(port, dirs)
        power = power * trans * gain
    start = origin[0] if origin.shape[0] == 1 else origin
    if beams.t0 is not None:      # the ends the caller keeps for the scan (no port)
        t0, t1 = beams.t0[keep], beams.t1[keep]
    else:
        t0, t1 = box_interval(start, dirs, grid.lo, grid.hi)
        if len(objects):
            t1 = np.minimum(t1, intersect(objects, start, dirs).t)
    beams = Beams(np.ascontiguousarray(origin), dirs, power, t0, t1, np.zeros(t0.size))
    deposit_beams(grid.args(), beams, float(src.sigma_t), 0.5 * float(grid.h.min()), phi, flux)
    return Field(phi, flux)


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
    d = _fibonacci(n)
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


def surface_irradiance(grid: Grid, field: Field, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """P1 irradiance onto surfaces (outward normal n, facing the medium): max(0, φ/4 − F·n/2)."""
    phi, flux = np.empty(points.shape[0]), np.empty((points.shape[0], 3))
    sample_fields(grid.args(), field.phi, field.flux, np.ascontiguousarray(points, float), phi, flux)
    return np.maximum(phi / 4.0 - 0.5 * (flux * normals).sum(1), 0.0)


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


class ViewTable(NamedTuple):
    """The coarse view rays of a whole frame and where each pixel reads them (the same for every pattern):
    their origins ((1, 3) the pinhole, or (k, 3)) and directions (k, 3), their medium entry t0 and exit t1,
    the coarse grid (gh, gw), and per pixel and neighbour ray ``index``, ``frac`` (h·w, 4) of
    :func:`~polarstripe.sim.frame_kernels.view_depths`."""

    origins: np.ndarray
    rays: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    gh: int
    gw: int
    index: np.ndarray
    frac: np.ndarray


def camera_rays(cam, pixels, rays_of=None) -> tuple[np.ndarray, np.ndarray]:
    """Origins ((1, 3): the pinhole) and directions (n, 3) of the camera rays of ``pixels`` ((n, 2) (row,
    col), fractional allowed); ``rays_of(pixels)``, where given, returns them per ray (a camera behind a
    port)."""
    if rays_of is not None:
        return rays_of(pixels)
    return np.asarray(cam.position, float).reshape(1, 3), pixel_rays(cam, pixels)


def _coarse_rays(grid: Grid, cam, coarse: tuple[int, int], rays_of=None):
    gw, gh = max(min(coarse[0], cam.w), 2), max(min(coarse[1], cam.h), 2)
    gr, gc = np.linspace(0, cam.h - 1, gh), np.linspace(0, cam.w - 1, gw)
    GR, GC = np.meshgrid(gr, gc, indexing="ij")
    origins, rays = camera_rays(cam, np.stack([GR.ravel(), GC.ravel()], 1), rays_of)
    t0, t1 = box_interval(origins[0] if origins.shape[0] == 1 else origins, rays, grid.lo, grid.hi)
    return origins, rays, np.maximum(t0, 0.0), t1, gh, gw


def view_table(grid: Grid, cam, x_end: np.ndarray, coarse: tuple[int, int], steps: int,
               rays_of=None) -> ViewTable:
    """The :class:`ViewTable` of a whole frame of ``cam`` whose pixels' view paths end at ``x_end``
    (``rays_of``: :func:`camera_rays`)."""
    origins, rays, t0, t1, gh, gw = _coarse_rays(grid, cam, coarse, rays_of)
    index, frac = np.empty((cam.h * cam.w, 4), np.int32), np.empty((cam.h * cam.w, 4))
    x_end = np.ascontiguousarray(x_end, float)
    in_bands(cam.h, lambda a, b: view_depths((cam.h, cam.w, gh, gw), t0, t1, int(steps), x_end, index, frac,
                                             a, b), min_size=16)
    return ViewTable(origins, rays, t0, t1, gh, gw, index, frac)


def view_integral(grid: Grid, fields: list[Field], view_args: ViewArgs, cam, pixels, x_end: np.ndarray,
                  coarse: tuple[int, int], steps: int, table: ViewTable | None = None,
                  rays_of=None) -> np.ndarray:
    """∫ J_i(C + x d, −d) e^{−σ(x − x₀)} dx from the medium's entry x₀ to ``x_end`` (per ray, flat) of each
    field i, for every pixel (a coarse grid of ``coarse`` = (w, h) rays, interpolated bilinearly between them
    at each pixel's own depth; ``table``: its :func:`view_table`, kept from an earlier frame) or for the
    requested ``pixels`` (their own rays); the rays start at the pinhole, or where ``rays_of``
    (:func:`camera_rays`) says. Returns (k, n)."""
    phi = np.ascontiguousarray(np.stack([f.phi for f in fields]))
    flux = np.ascontiguousarray(np.stack([f.flux for f in fields]))
    if pixels is None:
        table = table or view_table(grid, cam, x_end, coarse, steps, rays_of)
        origins, rays, t0, t1 = table.origins, table.rays, table.t0, table.t1
    else:
        origins, rays = camera_rays(cam, pixels, rays_of)
        t0, t1 = box_interval(origins[0] if origins.shape[0] == 1 else origins, rays, grid.lo, grid.hi)
        t0 = np.maximum(t0, 0.0)
    cum = np.empty((len(fields), rays.shape[0], int(steps) + 1))         # every entry written
    view_cumulative(grid.args(), phi, flux, view_args._replace(origin=np.ascontiguousarray(origins, float)),
                    np.ascontiguousarray(rays), t0, t1, cum)
    out = (np.empty if pixels is None else np.zeros)((len(fields), x_end.size))   # a frame: every pixel
    if pixels is None:
        in_bands(cam.h, lambda a, b: view_gather((cam.h, cam.w, table.gh, table.gw), cum, table.index,
                                                 table.frac, out, a, b), min_size=16)
    else:
        n = rays.shape[0]
        view_lookup((n, 1, n, 1), t0, t1, cum, np.ascontiguousarray(x_end, float), out)
    return out
