"""All orders of scattering: D, A, B of a frame with the light scattered more than once (docs/physics.md §10).

The terms, in the similarity-scaled medium of :mod:`polarstripe.sim.similarity` (σ̃_t, σ̃_s, P̃):

* D — the unscattered direct light, exactly as single scattering has it (e^{−σ_t(ℓ_LO + ℓ_CO)}).
* quasi-direct light on the object: the same formula with σ̃_t (direct plus forward-scattered light), its
  forward-scattered part spread on the object (:mod:`polarstripe.sim.psf`): the pattern widens and softens.
* single wide-angle scattering: the paper's A and B with the exact single-scattering integrators
  (:mod:`polarstripe.sim.transport`, :mod:`polarstripe.sim.surface_term`), P̃ and σ̃ (Nakajima & Tanaka's
  correction: σ̃_s P̃ = σ_s P at wide angles, so B keeps its exact backscatter phase function and Mueller DOP).
* orders ≥ 2 on a grid (:mod:`polarstripe.sim.multiple`): B from the emission of the scattered field along
  the view rays, A from its irradiance on the object.
* B's polarization (docs/physics.md §10.4): every cone scattering keeps r_c of it and every further
  wide-angle scattering κ, so its polarized part travels with the extinction σ_p (single wide-angle
  scattering: the same line integral's Stokes sums; orders ≥ 2: a grid chain with σ_p, order k weighted
  by κ^k, in the orientation of the single wide-angle scattering at the pixel).
* the objects' glow: each object's reflected light (exitance ρE) scattered at wide angles toward the camera
  (and onward, and back onto the objects), from the same grid with the objects as Lambertian sources; in A.
* the object's radiance blurred on its way to the camera by the forward cone (:mod:`polarstripe.sim.psf`).

A is everything that touched an object except D, B everything that did not: S = D + A stays the (unpolarized)
object signal and B the veiling light, so the analyzer model of docs/physics.md §4 is unchanged.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
from polarstripe.heap import shared_zeros
from polarstripe.sim import geometry_cache
from polarstripe.sim.backscatter import (
    add_circular_orders,
    add_made_orders,
    add_polarized_orders,
    b_cone,
    b_single,
    geo,
    polarized_source,
    polarized_steps,
    rays,
    scaled_source,
)
from polarstripe.sim.frame_kernels import field_irradiance, half_fix, half_up, plane_irradiance
from polarstripe.sim.geometry import box_interval, occluded, projector_coords, segment_length_in_box
from polarstripe.sim.glow import glow_steps
from polarstripe.sim.grid_kernels import ViewArgs, segment_lengths
from polarstripe.sim.grid_sources import (
    source_beams,
    source_field,
    view_integral,
    view_table,
)
from polarstripe.sim.multiple import Field, Grid, GridSolve, make_grid
from polarstripe.sim.orders import OrdersPlan
from polarstripe.sim.patterns import column_order, lit_in_columns, pattern_lit
from polarstripe.sim.psf import halo_table, mixture, spread
from polarstripe.sim.psf_frame import object_radiance
from polarstripe.sim.psf_stencil import stencil_blur
from polarstripe.sim.surface import surface_info
from polarstripe.sim.surface_field import View, camera_frame_stokes, single_parts
from polarstripe.sim.threads import in_bands
from polarstripe.sim.transport import Source, direct


@dataclasses.dataclass(frozen=True)
class HigherSettings:
    """Grid cells along the box's longest side, the orders computed one by one before the geometric tail
    (:func:`~polarstripe.sim.multiple.solve_orders`; ``glow_orders`` for the glow), the view rays' coarse grid
    divisor and depth steps,
    the glow's patch spacing in cells and directions per patch, the beam oversampling of the source, and the
    divisor of the resolution at which B's single wide-angle scattering is computed (1: every pixel),
    whether A's single wide-angle scattering is the exact integral (else the grid's once-scattered field),
    and whether whole frames of at least 640×480 compute everything but D and the albedo at half
    resolution (``preview``)."""

    cells: int = 16
    orders: int = 4
    glow_orders: int = 2
    view_div: int = 16
    view_steps: int = 24
    patch_cells: float = 1.0
    glow_dirs: int = 36
    oversample: float = 1.0
    b_div: int = 1
    a1_exact: bool = True
    half_res: bool = False

    def __post_init__(self):
        from polarstripe.sim.scene import SceneError

        ints = {"cells": (2, 128), "orders": (1, 200), "glow_orders": (1, 200), "view_div": (1, 64),
                "view_steps": (2, 4096), "glow_dirs": (4, 4096), "b_div": (1, 64)}
        for key, (lo, hi) in ints.items():
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise SceneError(f"fidelity.higher.{key} must be an integer in [{lo}, {hi}], got {v!r}")
        for key in ("patch_cells", "oversample"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.05 <= v <= 20:
                raise SceneError(f"fidelity.higher.{key} must be a number in [0.05, 20], got {v!r}")
        for key in ("a1_exact", "half_res"):
            if not isinstance(getattr(self, key), bool):
                raise SceneError(f"fidelity.higher.{key} must be true or false, got {getattr(self, key)!r}")


HALF_MIN = (640, 480)      # half resolution only where the half frame still resolves stripes (≥ 320×240)


def _direct_pair(view: View, src: Source, ssrc: Source, need) -> tuple[np.ndarray, np.ndarray]:
    """D (exact, σ_t) and the quasi-direct object radiance per unit albedo (σ̃_t both ways), per ray.

    Whole frames take both at every hit the source sees from the scene's geometry cache (the same for every
    pattern) and keep the lit ones; the kernels compute each point on its own, so this is bit-identical to
    computing only the lit points."""
    scene, pat, _, cam, _, hits, surf, _ = view
    n = hits.t.size
    want_d = "D" in need or ("A" in need and view.pixels is not None)       # pixels: A = stencil − D
    d, quasi = (np.zeros(n) if want else np.empty(0) for want in (want_d, "A" in need))  # only what is asked
    if view.pixels is None and geometry_cache.enabled():
        def visible():
            hit = np.nonzero(surf.object_id >= 0)[0]
            return hit[~occluded(scene.objects, src.position, hits.point[hit])]

        seen = geo(view, "seen", visible)
        if seen.size == 0:
            return d, quasi
        if src.frame is None:
            lit = seen
        else:
            coords = geo(view, "seen_coords", lambda: projector_coords(src.frame, hits.point[seen]))
            if pat.kind in ("flood", "stripe"):       # by bisection in the seen points' columns
                lit = seen[lit_in_columns(pat, src.frame.w, geo(view, "seen_columns",
                                                                lambda: column_order(src.frame, coords)))]
            else:
                lit = seen[pattern_lit(pat, src.frame, None, coords)]

        def every(source, albedo):
            out = np.zeros(n)
            out[seen] = direct(source, scene.objects, cam.position, hits.point[seen], hits.normal[seen],
                               albedo, np.ones(seen.size, bool))
            return out

        if want_d:
            d[lit] = geo(view, "D", lambda: every(src, surf.albedo[seen]))[lit]
        if "A" in need:
            quasi[lit] = geo(view, ("quasi", ssrc.sigma_t), lambda: every(ssrc, np.ones(seen.size)))[lit]
        return d, quasi
    hit = np.nonzero(surf.object_id >= 0)[0]
    if hit.size == 0:
        return d, quasi
    lit = hit[pattern_lit(pat, src.frame, hits.point[hit])]
    lit = lit[~occluded(scene.objects, src.position, hits.point[lit])]
    ones = np.ones(lit.size, bool)
    if want_d:
        d[lit] = direct(src, scene.objects, cam.position, hits.point[lit], hits.normal[lit], surf.albedo[lit],
                        ones)
    if "A" in need:
        quasi[lit] = direct(ssrc, scene.objects, cam.position, hits.point[lit], hits.normal[lit],
                            np.ones(lit.size), ones)
    return d, quasi


def object_light(view: View, ssrc: Source, plan: OrdersPlan, quasi: np.ndarray, rest_unit: np.ndarray,
                 ells: tuple[np.ndarray, np.ndarray], rays_of=None, light=None):
    """The object light after both forward-cone blurs: whole frames (P, H) with A = ρ·P + H (beyond D,
    :func:`polarstripe.sim.psf_frame.object_radiance`); requested pixels the object radiance D + A (stencils).
    ``quasi`` and ``rest_unit`` (Ã) per unit albedo, ``ells`` the in-medium lengths source → hit and
    camera → hit; ``rays_of``, ``light``: the camera's rays and the quasi-direct irradiance through ports
    (:func:`polarstripe.sim.psf_stencil.stencil_blur`)."""
    scene, _, _, cam, dirs, hits, surf, pixels = view
    sc, ph = plan.scaled, scene.medium.phase
    table = halo_table(ph.model, float(ph.g), float(sc.phase.cos_c))
    fss = sc.f * scene.medium.sigma_s
    if pixels is None:
        return object_radiance(view, table, fss, quasi, rest_unit, ells)
    hit = surf.object_id >= 0
    ells, depth = [e.copy() for e in ells], np.where(hit, view.hits.t, 0.0)
    probe = _probe(view, ssrc) if not hit.all() else None
    if probe is not None:                  # pixels beside the objects: the halo of a nearby object point
        for e, v in zip(ells, probe[:2], strict=True):
            e[~hit] = v
        depth[~hit] = probe[2]
    legs = []
    for ell in ells:
        n, rms = spread(table, fss, ell)
        legs.append((n, rms, np.stack([mixture(table, float(v)) for v in n])))
    return stencil_blur(view, ssrc, legs, rest_unit, depth, rays_of, light)


def _probe(view: View, ssrc: Source):
    """(ℓ_L, ℓ_C, distance) of the object point on the camera's axis (None if the axis meets no object)."""
    from polarstripe.sim.geometry import intersect

    cam = view.cam
    h = intersect(view.scene.objects, cam.position, cam.f[None, :])
    if not np.isfinite(h.t[0]):
        return None
    p = h.point
    lo, hi = np.asarray(ssrc.box_lo, float), np.asarray(ssrc.box_hi, float)
    ell = [float(segment_length_in_box(a, p, lo, hi)[0]) for a in (ssrc.position, cam.position)]
    return ell[0], ell[1], float(h.t[0])


def _lengths(start, view: View, ssrc: Source) -> np.ndarray:
    """In-medium length [m] from ``start`` to each ray's hit (0 where nothing is hit)."""
    out = np.zeros(view.hits.t.size)
    hit = np.nonzero(view.surf.object_id >= 0)[0]
    seg = np.empty(hit.size)
    segment_lengths(np.asarray(start, float), np.ascontiguousarray(view.hits.point[hit]),
                    np.asarray(ssrc.box_lo, float), np.asarray(ssrc.box_hi, float), seg)
    out[hit] = seg
    return out


def _constant_stokes(view: View, src: Source, b: np.ndarray):
    """``dop.model = "constant"``: every order carries the stated p times the source's state (a measured
    backscatter DOP; :func:`~polarstripe.sim.surface_field.camera_frame_stokes`)."""
    return camera_frame_stokes(src, view.scene, view.cam, view.dirs, b, None, None)


def higher_steps(view: View, src: Source, plan: OrdersPlan, need, settings: HigherSettings | None = None):
    """D, A, B, Bq, Bu, Bv per ray (flat) with all orders of scattering (module docstring), as steps: a
    generator that yields the frame's grid solves (:class:`~polarstripe.sim.multiple.GridSolve`) and returns
    the components (:func:`~polarstripe.sim.multiple.answer` runs it alone; a scan's frames step together
    and hand their solves over as one batch, :mod:`polarstripe.sim.scan_render`)."""
    st = settings or HigherSettings()
    cam = view.cam
    if st.half_res and view.pixels is None and cam.w >= HALF_MIN[0] and cam.h >= HALF_MIN[1] and \
            cam.w % 2 == 0 == cam.h % 2:
        return (yield from _half_resolution(view, src, plan, need, st))
    return (yield from _components(view, src, plan, need, st))


def _half_resolution(view: View, src: Source, plan: OrdersPlan, need, st: HigherSettings):
    """Whole frames at ``preview`` of at least 640×480: everything smooth at half resolution, bilinear up (A's
    per-unit-albedo part within each object), D and the albedo at full resolution: A = ρ·P↑ + H↑. Smaller
    frames stay at full resolution (their half would blur a scan's stripes)."""
    from polarstripe.sim.geometry import PinholeFrame

    cam = view.cam
    half = PinholeFrame(cam.position, cam.f, cam.r, cam.u, 2 * cam.s, cam.w // 2, cam.h // 2)

    def geometry():
        dirs, hits = rays(view.scene, half)
        return dirs, hits, surface_info(view.scene.objects, hits)

    small = View(view.scene, view.pattern, view.fid, half, *geo(view, "half", geometry, camera_only=True),
                 None)
    _, p_half, h_half, b, bq, bu, bv = yield from _components(small, src, plan, need, st, parts=True)
    d, _ = _direct_pair(view, src, scaled_source(src, plan), tuple(k for k in need if k == "D"))
    d = d if d.size else np.zeros(cam.w * cam.h)
    fields = (h_half, b, bq, bu, bv) if bv.any() else (h_half, b, bq, bu)      # (V is 0 for linear light)
    smooth = tuple(np.ascontiguousarray(x).reshape(half.h, half.w) for x in fields)
    out, a = np.empty((len(smooth) - 1, cam.w * cam.h)), np.empty(cam.w * cam.h)   # every pixel written
    ids_small = small.surf.object_id.reshape(half.h, half.w)
    fix, fix_start = geo(view, "half_fix", lambda: half_fix(view.surf.object_id.reshape(cam.h, cam.w),
                                                            ids_small, view.surf.albedo), camera_only=True)
    args = (smooth, p_half.reshape(half.h, half.w), ids_small, view.surf.object_id, view.surf.albedo, fix,
            fix_start, a, out)
    in_bands(cam.h, lambda r0, r1: half_up(*args, r0, r1), min_size=16)
    return d, a, out[0], out[1], out[2], out[3] if len(smooth) > 4 else shared_zeros(a.size)


class RayGeometry(NamedTuple):
    """Per camera ray, the same for every pattern (kept per scene for whole frames): the medium grid's
    interval [t0, t1], the view path's end x_end = min(t1, hit) and start x0 = max(t0, 0), the in-medium
    length ℓ_C of rays that hit an object (0 elsewhere), the hit points and normals (contiguous) and their one
    normal where they all share it (a plane seen alone; else None)."""

    t0: np.ndarray
    t1: np.ndarray
    x_end: np.ndarray
    x0: np.ndarray
    ell_c: np.ndarray
    hit_points: np.ndarray
    hit_normals: np.ndarray
    one_normal: np.ndarray | None


def _ray_geometry(view: View, grid: Grid) -> RayGeometry:
    def make():
        t0, t1 = box_interval(view.cam.position, view.dirs, grid.lo, grid.hi)
        x_end, x0 = np.minimum(t1, view.hits.t), np.maximum(t0, 0.0)
        hit = view.surf.object_id >= 0
        ell_c = np.where(hit & (t1 > t0), x_end - x0, 0.0)     # the view ray in the medium
        normals = np.ascontiguousarray(view.hits.normal[hit])
        one = normals[0].copy() if normals.size and (normals == normals[0]).all() else None
        return RayGeometry(t0, t1, x_end, x0, ell_c, np.ascontiguousarray(view.hits.point[hit]), normals, one)

    return geo(view, ("rays", tuple(grid.lo), tuple(grid.hi)), make, camera_only=True)


def _irradiance(grid: Grid, field: Field, points: np.ndarray, normals: np.ndarray,
                normal: np.ndarray | None = None) -> np.ndarray:
    """The P1 irradiance max(0, φ/4 − F·n/2) of ``field`` at surface points (one compiled pass); ``normal``:
    the one outward normal of them all (a plane), which makes φ/4 − F·n/2 one field to sample."""
    out, args = np.empty(points.shape[0]), grid.args()
    if normal is not None:
        e_field = np.ascontiguousarray(field.phi / 4.0 - 0.5 * (field.flux @ normal))
        in_bands(out.size, lambda a, b: plane_irradiance(args, e_field, points[a:b], out[a:b]))
        return out
    in_bands(out.size, lambda a, b: field_irradiance(args, field.phi, field.flux, points[a:b], normals[a:b],
                                                     out[a:b]))
    return out


def _components(view: View, src: Source, plan: OrdersPlan, need, st: HigherSettings, parts: bool = False):
    """D, A, B, Bq, Bu, Bv (or, ``parts``, D, P, H, B, Bq, Bu, Bv with A = ρ·P + H) per ray, flat; steps
    that yield the grid solves. The source's beams are kept per scene (the pattern only weights them)."""
    sc = plan.scaled
    ssrc = scaled_source(src, plan)
    n = view.dirs.shape[0]
    D, quasi = _direct_pair(view, src, ssrc, need if not parts else tuple(k for k in need if k != "D"))
    hit = view.surf.object_id >= 0
    want_a = "A" in need and bool(hit.any())
    b_made = "B" in need and sc.sigma_s > 0
    A = None if want_a else np.zeros(n)                                  # None: made below
    B, Bq, Bu, Bv = (None,) * 4 if b_made else tuple(np.zeros(n) for _ in range(4))
    if not (want_a or "B" in need) or sc.sigma_s <= 0:
        A = np.zeros(n) if A is None else A
        D = D if D.size == n else np.zeros(n)
        return (D, np.zeros(n), A, B, Bq, Bu, Bv) if parts else (D, A, B, Bq, Bu, Bv)
    grid = make_grid(ssrc.box_lo, ssrc.box_hi, st.cells)
    dop = view.scene.medium.dop
    pol = "p" in need and "B" in need and dop.model == "rayleigh"
    beams = geo(view, ("beams", grid, st.oversample),
                lambda: source_beams(grid, ssrc, view.scene.objects, st.oversample))
    orders = yield GridSolve(grid, source_field(grid, ssrc, view.scene.objects, st.oversample, beams=beams),
                             sc.sigma_t, sc.sigma_s, sc.g_tilde, st.orders)
    rg = _ray_geometry(view, grid)
    x_end = rg.x_end
    fields = [orders.total] if "B" in need else []
    sigmas = [sc.sigma_t] * len(fields)
    lin, circ = src.linear_circular
    if pol:           # the polarized part travels with σ_p, the circular with σ_pV (docs/physics.md §10.4)
        psrc = polarized_source(src, plan, view.scene)
        if lin != 0.0:
            fields.append((yield from polarized_steps(psrc, plan, view.scene, st, grid, beams=beams)))
            sigmas.append(psrc.sigma_pol)
        if circ != 0.0:
            fields.append((yield from polarized_steps(psrc, plan, view.scene, st, grid, True, beams=beams)))
            sigmas.append(psrc.sigma_pol_v)
    if want_a:
        seen, glow_scattered = yield from glow_steps(view, ssrc, plan, st, grid, orders.total)
        fields.append(seen)
        sigmas.append(sc.sigma_t)
    cam = view.cam
    c = np.full(len(fields), sc.sigma_s / (4 * np.pi))
    args = ViewArgs(c, np.full(len(fields), sc.g_tilde), np.array(sigmas, float),
                    np.asarray(cam.position, float).reshape(1, 3))
    coarse = (min(cam.w, max(cam.w // st.view_div, 16)), min(cam.h, max(cam.h // st.view_div, 12)))
    table = None if view.pixels is not None else geo(view, ("view_table", grid, coarse, st.view_steps),
                                                     lambda: view_table(grid, cam, x_end, coarse,
                                                                        st.view_steps), camera_only=True)
    seen_vals = view_integral(grid, fields, args, view.cam, view.pixels, x_end, coarse, st.view_steps, table)
    if "B" in need:
        B, Bq, Bu, Bv = b_single(view, psrc if pol else ssrc, need, st.b_div, x_end)
        single = (B.copy(), Bq.copy(), Bu.copy()) if pol and abs(lin) < 1.0 else None
        sp = dataclasses.replace(src, sigma_pol=psrc.sigma_pol, sigma_pol_v=psrc.sigma_pol_v) if pol else src
        cone = b_cone(view, sp, plan, need, rg.x0)
        if cone is not None:
            B += cone[0]
            Bq += cone[1]
            Bu += cone[2]
            Bv += cone[3]
        if pol:
            delta = float(dop.depolarization)
            k = 1
            if lin != 0.0:
                Bq, Bu = add_polarized_orders(Bq, Bu, seen_vals[k], (1.0 - delta) * abs(lin))
                k += 1
            if circ != 0.0:
                Bv = add_circular_orders(Bv, seen_vals[k], -(1.0 - 2.0 * delta) * circ)
            if abs(lin) < 1.0:           # the light that is not linearly polarized: what orders ≥ 2 make
                Bq, Bu = add_made_orders(Bq, Bu, *single, seen_vals[0], 1.0 - abs(lin))
        B += seen_vals[0]
        if "p" in need and dop.model == "constant":
            Bq, Bu, Bv = _constant_stokes(view, src, B)
    if want_a:
        hp, hn, ell_c = rg.hit_points, rg.hit_normals, rg.ell_c
        ell_l = geo(view, "ell_l", lambda: _lengths(ssrc.position, view, ssrc))
        rest = np.zeros(n)
        if st.a1_exact:
            unit = view._replace(surf=dataclasses.replace(view.surf, albedo=np.ones(n)))
            rest = single_parts(unit, ssrc, ("A",))[1]                   # per unit albedo
            e2 = _irradiance(grid, orders.total - orders.first + glow_scattered, hp, hn, rg.one_normal)
        else:
            e2 = _irradiance(grid, orders.total + glow_scattered, hp, hn, rg.one_normal)
        att = geo(view, ("att_c", sc.sigma_t), lambda: np.exp(-sc.sigma_t * ell_c[hit]), camera_only=True)
        rest[hit] += e2 * att / np.pi
        light = object_light(view, ssrc, plan, quasi, rest, (ell_l, ell_c))
        if parts:
            h = light[1]
            h += seen_vals[-1]
            return D, light[0], h, B, Bq, Bu, Bv
        if view.pixels is None:
            A = view.surf.albedo * light[0]                  # ρ·P + H + glow, in place (one array)
            A += light[1]
            A += seen_vals[-1]
        else:
            A = np.maximum(light - D, 0.0) + seen_vals[-1]
    if parts:
        return D, np.zeros(n), A, B, Bq, Bu, Bv
    return (D if "D" in need else np.zeros(n)), A, B, Bq, Bu, Bv
