"""The public entry point of the light-transport model: components D, A, B per pixel, and frames.

>>> from polarstripe.sim.render import render_components, render_frame
>>> from polarstripe.sim.scene import load_scene
>>> comp = render_components(load_scene(None), "stripe:14/30", "preview")   # doctest: +SKIP
>>> dn, comp = render_frame(load_scene(None), "flood", 90.0, "standard", seed=1)   # doctest: +SKIP
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from polarstripe.sim.geometry import (
    box_interval,
    intersect,
    occluded,
    pinhole_frame,
    pixel_rays,
    projector_coords,
)
from polarstripe.sim.kernel_records import Stokes
from polarstripe.sim.kernels import camera_stokes
from polarstripe.sim.patterns import Pattern, lit_intervals, parse_pattern, stripe_columns
from polarstripe.sim.polarization import analyzer
from polarstripe.sim.scene import PlaneObject, Scene, SceneError
from polarstripe.sim.sensor import expose
from polarstripe.sim.surface import SurfaceInfo, surface_info
from polarstripe.sim.surface_grid import plane_stripe_field
from polarstripe.sim.surface_term import surface_scatter_beams
from polarstripe.sim.transport import (
    Source,
    direct,
    line_radiance,
    make_source,
    surface_scatter,
)


@dataclass(frozen=True)
class Fidelity:
    """Sample counts: ξ nodes per lit interval; for A the pattern-pixel rule's nodes per side (``a_side``,
    pinhole flood/stripe: :mod:`surface_term`; 0 = always the hemisphere rule), the hemisphere rule's θ
    nodes per piece × φ azimuths (point source, checkers), and the A grid (w, h) (None: every pixel): for a
    flood or stripe on a plane w uniform pattern columns (plus graded ones at the stripe edges, a sparser set
    when w < 12) × h pattern rows (:mod:`surface_grid`); other objects a camera grid of 3w × 3h."""

    name: str
    xi_nodes: int
    hemi_theta: int
    hemi_phi: int
    a_grid: tuple[int, int] | None
    a_side: int = 0


FIDELITY = {
    "preview": Fidelity("preview", 4, 2, 6, (10, 4), 4),
    "standard": Fidelity("standard", 6, 4, 12, (12, 6), 4),
    "reference": Fidelity("reference", 64, 16, 48, None, 24),
}

_CAMERA_GRID = 3      # objects other than planes: an A grid of a_grid × this over the image


def resolve_fidelity(fidelity: str | Fidelity) -> Fidelity:
    """A named level (``preview``, ``standard``, ``reference``), a :class:`Fidelity`, or
    ``"xi=N,theta=N,phi=N,side=N,grid=WxH|none"`` (explicit counts, unspecified ones from ``standard``)."""
    if isinstance(fidelity, Fidelity):
        return fidelity
    if fidelity in FIDELITY:
        return FIDELITY[fidelity]
    base = FIDELITY["standard"]
    kw = {"xi_nodes": base.xi_nodes, "hemi_theta": base.hemi_theta, "hemi_phi": base.hemi_phi,
          "a_grid": base.a_grid, "a_side": base.a_side}
    try:
        for part in str(fidelity).split(","):
            k, v = part.split("=")
            k = k.strip()
            if k == "grid":
                kw["a_grid"] = None if v.strip() == "none" else tuple(int(x) for x in v.lower().split("x"))
            else:
                kw[{"xi": "xi_nodes", "theta": "hemi_theta", "phi": "hemi_phi", "side": "a_side"}[k]] = int(v)
        fid = Fidelity(str(fidelity), **kw)
        if min(fid.xi_nodes, fid.hemi_theta, fid.hemi_phi) < 1 or fid.a_side < 0 or (
                fid.a_grid and min(fid.a_grid) < 2):
            raise ValueError
        return fid
    except (ValueError, KeyError, TypeError):
        raise SceneError(f"fidelity {fidelity!r} is not preview, standard, reference or "
                         "'xi=N,theta=N,phi=N,side=N,grid=WxH|none'") from None


@dataclass
class Components:
    """Radiance components [W sr⁻¹ m⁻²] before the analyzer, each (h, w), or (n,) for requested pixels.

    D direct (eq. 11), A surface-scattered (eq. 12), B backscatter (eq. 13), Bq/Bu the backscatter's
    B-weighted linear Stokes in the camera frame (angles from image right toward image up), so p and χ
    follow; ``surface`` says which pixels see which object and the chart's bars.
    """

    D: np.ndarray
    A: np.ndarray
    B: np.ndarray
    Bq: np.ndarray
    Bu: np.ndarray
    surface: SurfaceInfo
    scene: Scene
    pattern: Pattern
    fidelity: Fidelity
    pixels: np.ndarray | None = None
    seconds: float = 0.0

    @property
    def S(self) -> np.ndarray:
        """Object signal S = D + A."""
        return self.D + self.A

    @property
    def p(self) -> np.ndarray:
        """Per-pixel backscatter DOP (B-weighted over the ray; 0 where B = 0)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.B > 0, np.clip(np.hypot(self.Bq, self.Bu) / self.B, 0.0, 1.0), 0.0)

    @property
    def chi_rad(self) -> np.ndarray:
        """Per-pixel angle of the backscatter polarization in the camera frame [rad]."""
        return 0.5 * np.arctan2(self.Bu, self.Bq)

    @property
    def object_mask(self) -> np.ndarray:
        """True where the pixel sees an object."""
        return self.surface.object_id >= 0

    def combine(self, other: Components, a: float, b: float) -> Components:
        """Linear combination a·self + b·other of the radiance fields (same pixels)."""
        return Components(a * self.D + b * other.D, a * self.A + b * other.A, a * self.B + b * other.B,
                          a * self.Bq + b * other.Bq, a * self.Bu + b * other.Bu, self.surface, self.scene,
                          self.pattern, self.fidelity, self.pixels, self.seconds + other.seconds)


def _pattern_lit(pattern: Pattern, frame, points: np.ndarray) -> np.ndarray:
    if frame is None:
        return np.ones(points.shape[0], bool)
    col, row, depth = projector_coords(frame, points)
    ok = (depth > 0) & (row >= 0) & (row < frame.h) & (col >= 0) & (col < frame.w)
    if pattern.kind == "stripe":
        c0, c1 = stripe_columns(pattern, frame.w)
        ok &= (col >= c0) & (col < c1)
    elif pattern.kind == "checker":
        shift = pattern.shift % (2 * pattern.size)
        ok &= (np.floor((col - shift) / pattern.size) + np.floor(row / pattern.size)) % 2 == 0
    return ok


def _a_field(src: Source, scene: Scene, fid: Fidelity, cam, hits, surf: SurfaceInfo, pixels) -> np.ndarray:
    """A per pixel: directly at requested pixels, else on the coarse grid and interpolated per object."""
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
    fields = _extend_planes(scene, cam, gdirs, gval, gobj, a_at)
    idx = np.nonzero(hit & ~done)[0]
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
        a_out[miss] = at(miss)
    return a_out


def _extend_planes(scene: Scene, cam, gdirs, gval, gobj, a_at) -> dict:
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


def render_components(scene: Scene, pattern: str | Pattern, fidelity: str | Fidelity = "standard",
                      pixels: np.ndarray | None = None,
                      need: tuple[str, ...] = ("D", "A", "B", "p")) -> Components:
    """Radiance components of one pattern (paper eqs. 11–13, physical form; docs/physics.md §0).

    Parameters
    ----------
    scene : Scene
    pattern : ``flood``, ``stripe:K/N``, ``checker:SIZE:SHIFT`` or a :class:`Pattern`.
    fidelity : ``preview`` | ``standard`` | ``reference`` | :class:`Fidelity` |
        ``"xi=..,theta=..,phi=..,grid=.."``.
    pixels : optional (n, 2) int array of (row, col): compute only these (cost scales with n; A exact there).
    need : components to compute (others are zeros): any of ``D``, ``A``, ``B`` and ``p`` (the backscatter
        polarization; without it Bq = Bu = 0, which saves ~40 % of the B cost).

    Returns
    -------
    Components with arrays of shape (h, w), or (n,) when ``pixels`` is given.
    """
    t_start = time.perf_counter()
    if not isinstance(scene, Scene):
        raise SceneError(f"scene must be a Scene (see load_scene), got {type(scene).__name__}")
    pat = parse_pattern(pattern)
    fid = resolve_fidelity(fidelity)
    if scene.projector.model == "point" and pat.kind != "flood":
        raise SceneError(f"pattern {str(pat)!r} needs projector.model = 'pinhole' "
                         "(the point source is flood only)")
    cam = pinhole_frame(scene.camera.position, scene.camera.look_at, scene.camera.up, scene.camera.fov_deg,
                        scene.camera.resolution)
    if pixels is not None:
        pixels = np.asarray(pixels)
        if pixels.ndim != 2 or pixels.shape[1] != 2 or not np.issubdtype(pixels.dtype, np.integer):
            raise SceneError(f"pixels must be an (n, 2) integer array of (row, col), got {pixels.shape}")
        if pixels.size and (pixels.min(axis=0) < 0).any() or (pixels.size and (
                pixels[:, 0].max() >= cam.h or pixels[:, 1].max() >= cam.w)):
            raise SceneError(f"pixels must lie inside the {cam.w}x{cam.h} image")
    black = scene.projector.black_level
    if black > 0 and pat.kind != "flood":
        clean = scene.replace(projector=scene.projector.replace(black_level=0.0))
        on = render_components(clean, pat, fid, pixels, need)
        flood = render_components(clean, "flood", fid, pixels, need)
        out = on.combine(flood, 1.0 - black, black)
        out.scene, out.seconds = scene, time.perf_counter() - t_start
        return out
    src = make_source(scene, pat)
    dirs = pixel_rays(cam, pixels)
    n = dirs.shape[0]
    hits = intersect(scene.objects, cam.position, dirs)
    surf = surface_info(scene.objects, hits)
    D, A, B, Bq, Bu = (np.zeros(n) for _ in range(5))
    hit = np.nonzero(surf.object_id >= 0)[0]
    if "D" in need and hit.size:
        lit_idx = hit[_pattern_lit(pat, src.frame, hits.point[hit])]          # shadow rays only where lit
        lit_idx = lit_idx[~occluded(scene.objects, src.position, hits.point[lit_idx])]
        pts = hits.point[lit_idx]
        D[lit_idx] = direct(src, scene.objects, cam.position, pts, hits.normal[lit_idx], surf.albedo[lit_idx],
                            np.ones(lit_idx.size, bool))
    if "A" in need and hit.size and src.sigma_s > 0:
        A = _a_field(src, scene, fid, cam, hits, surf, pixels)
    if "B" in need and src.sigma_s > 0:
        t0, t1 = box_interval(cam.position, dirs, src.box_lo, src.box_hi)
        t1 = np.minimum(t1, hits.t)
        lit = lit_intervals(pat, src.frame, cam.position, dirs, t0, t1)
        pol = "p" in need and scene.medium.dop.model == "rayleigh"
        res = line_radiance(src, cam.position, dirs, t0, lit, fid.xi_nodes, polarization=pol)
        B, q, u = res if pol else (res, None, None)
        if "p" in need:
            Bq, Bu = _camera_stokes(src, scene, cam, dirs, B, q, u)
    shape = (cam.h, cam.w) if pixels is None else (n,)
    surf = SurfaceInfo(*(a.reshape(shape) for a in (surf.object_id, surf.albedo, surf.chart_band,
                                                     surf.chart_high)))
    D, A, B, Bq, Bu = (a.reshape(shape) for a in (D, A, B, Bq, Bu))
    return Components(D, A, B, Bq, Bu, surf, scene, pat, fid, pixels, time.perf_counter() - t_start)


def _camera_stokes(src: Source, scene: Scene, cam, dirs, B, q, u):
    """Rotate the per-ray (q, u) sums from the scattering-plane frame into the camera frame (r, u axes)."""
    dop = scene.medium.dop
    if dop.model == "constant":
        chi = np.arctan2(src.e_field @ cam.u, src.e_field @ cam.r)
        return B * dop.p * src.dop_l * np.cos(2 * chi), B * dop.p * src.dop_l * np.sin(2 * chi)
    qc, uc = np.empty_like(B), np.empty_like(B)
    camera_stokes(np.asarray(src.position, float), np.asarray(cam.position, float),
                  np.ascontiguousarray(dirs), cam.r, cam.u, Stokes(B, q, u), qc, uc)
    return qc, uc


def render_frame(scene: Scene, pattern: str | Pattern, polarizer_deg: float | None = None,
                 fidelity: str | Fidelity = "standard", seed: int | np.random.Generator | None = None,
                 pixels: np.ndarray | None = None):
    """One simulated camera frame: components → analyzer (Malus) → EMVA 1288 sensor.

    Returns
    -------
    (dn, components): dn uint16 (h, w) digital numbers (``bits``-bit, clipped), and the Components.
    ``seed`` None uses ``camera.seed``.
    """

    comp = render_components(scene, pattern, fidelity, pixels)
    radiance = analyzer(comp, polarizer_deg)
    rng = scene.camera.seed if seed is None else seed
    return expose(radiance, scene.camera, rng, pixels=pixels), comp
