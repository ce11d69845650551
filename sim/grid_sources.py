"""What feeds the higher-order grid and what is read back from it (:mod:`polarstripe.sim.multiple`).

* :func:`source_field` — the quasi-direct light of the projector (or point source) as fluence and flux per
  cell: beams from the source through the lit pattern, each carrying I0·ΔΩ·e^{−σ̃_t s} per unit length
  (dV = s² ds dΩ cancels the 1/s² of the point source, so a cell receives exactly the power that crosses it),
  ending at the first object. A beam's weight is its solid angle times the lit fraction of its patch of
  pattern pixels, so the lit power is exact for stripes and checkers finer than the grid.
* the objects as Lambertian sources of the grid (the glow): :mod:`polarstripe.sim.grid_patches`.
* :func:`view_integral` — the in-scattered radiance J(Y, −d) = c(φ + 3g̃F·(−d)) integrated along the view
  rays with the view's attenuation, on a coarse set of rays with per-pixel depths.
* :func:`surface_irradiance` — the P1 irradiance E = φ/4 − F·n/2 onto a surface of outward normal n.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from polarstripe.sim.frame_kernels import view_depths, view_gather
from polarstripe.sim.geometry import box_interval, intersect, pixel_rays
from polarstripe.sim.grid_kernels import (
    Beams,
    ViewArgs,
    deposit_beams,
    sample_fields,
    view_cumulative,
    view_lookup,
)
from polarstripe.sim.multiple import Field, Grid
from polarstripe.sim.patterns import gray_lit, sheet_columns
from polarstripe.sim.port import water_rays
from polarstripe.sim.port_kernels import source_port_gain
from polarstripe.sim.threads import in_bands
from polarstripe.sim.transport import Source

_MAX_BEAMS = 60000


def fibonacci_sphere(n: int) -> np.ndarray:
    """n unit vectors spread evenly over the sphere (a Fibonacci lattice), (n, 3)."""
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
        return SourceBeams(fibonacci_sphere(m), np.full(m, src.intensity * 4 * math.pi / m), None)
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


def surface_irradiance(grid: Grid, field: Field, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """P1 irradiance onto surfaces (outward normal n, facing the medium): max(0, φ/4 − F·n/2)."""
    phi, flux = np.empty(points.shape[0]), np.empty((points.shape[0], 3))
    sample_fields(grid.args(), field.phi, field.flux, np.ascontiguousarray(points, float), phi, flux)
    return np.maximum(phi / 4.0 - 0.5 * (flux * normals).sum(1), 0.0)


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
