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
from polarstripe.heap import keep_freed, shared_zeros
from polarstripe.sim.geometry import intersect, pinhole_frame, pixel_rays
from polarstripe.sim.geometry_cache import cached, camera_only
from polarstripe.sim.higher import HigherSettings, higher_steps
from polarstripe.sim.multiple import answer
from polarstripe.sim.orders import OrdersPlan, plan_orders
from polarstripe.sim.patterns import PatternSpec, parse_pattern
from polarstripe.sim.polarization import analyzer
from polarstripe.sim.port_render import has_port, port_parts
from polarstripe.sim.scene import Scene, SceneError
from polarstripe.sim.sensor import expose
from polarstripe.sim.surface import SurfaceInfo, surface_info
from polarstripe.sim.surface_field import View, single_parts
from polarstripe.sim.transport import make_source

keep_freed()        # a frame's arrays reuse the last frame's memory (heap.py)


@dataclass(frozen=True)
class Fidelity:
    """Sample counts: ξ nodes per lit interval; for A the pattern-pixel rule's nodes per side (``a_side``,
    pinhole flood/stripe: :mod:`surface_term`; 0 = always the hemisphere rule), the hemisphere rule's θ
    nodes per piece × φ azimuths (point source, checkers), and the A grid (w, h) (None: every pixel): for a
    flood or stripe on a plane w uniform pattern columns (plus graded ones at the stripe edges, a sparser set
    when w < 12) × h pattern rows (:mod:`surface_grid`); other objects a camera grid of 3w × 3h. The higher
    orders (:mod:`polarstripe.sim.higher`): ``higher`` (grid cells along the tank's longest side, the orders'
    tolerance, …; :class:`~polarstripe.sim.higher.HigherSettings`)."""

    name: str
    xi_nodes: int
    hemi_theta: int
    hemi_phi: int
    a_grid: tuple[int, int] | None
    a_side: int = 0
    higher: HigherSettings = HigherSettings()


FIDELITY = {
    "preview": Fidelity("preview", 4, 2, 6, (10, 4), 4,
                        HigherSettings(cells=10, orders=3, glow_orders=1, view_div=16, view_steps=16,
                                       patch_cells=1.5, glow_dirs=16, oversample=0.7, b_div=2,
                                       a1_exact=False, half_res=True)),
    "standard": Fidelity("standard", 6, 4, 12, (12, 6), 4, HigherSettings(b_div=3, a1_exact=False)),
    "reference": Fidelity("reference", 64, 16, 48, None, 24,
                          HigherSettings(cells=32, orders=16, glow_orders=8, view_div=4, view_steps=96,
                                         patch_cells=0.5, glow_dirs=144, oversample=2.0, a1_exact=False)),
}


def resolve_fidelity(fidelity: str | Fidelity) -> Fidelity:
    """A named level (``preview``, ``standard``, ``reference``), a :class:`Fidelity`, or
    ``"xi=N,theta=N,phi=N,side=N,grid=WxH|none,cells=N"`` (explicit counts, unspecified ones from
    ``standard``; ``cells`` is the higher orders' grid)."""
    if isinstance(fidelity, Fidelity):
        return fidelity
    if fidelity in FIDELITY:
        return FIDELITY[fidelity]
    base = FIDELITY["standard"]
    kw = {"xi_nodes": base.xi_nodes, "hemi_theta": base.hemi_theta, "hemi_phi": base.hemi_phi,
          "a_grid": base.a_grid, "a_side": base.a_side}
    cells = base.higher.cells
    try:
        for part in str(fidelity).split(","):
            k, v = part.split("=")
            k = k.strip()
            if k == "grid":
                kw["a_grid"] = None if v.strip() == "none" else tuple(int(x) for x in v.lower().split("x"))
            elif k == "cells":
                cells = int(v)
            else:
                kw[{"xi": "xi_nodes", "theta": "hemi_theta", "phi": "hemi_phi", "side": "a_side"}[k]] = int(v)
        fid = Fidelity(str(fidelity), **kw, higher=HigherSettings(cells=cells))
        if min(fid.xi_nodes, fid.hemi_theta, fid.hemi_phi) < 1 or fid.a_side < 0 or (
                fid.a_grid and min(fid.a_grid) < 2) or not 2 <= cells <= 128:
            raise ValueError
        return fid
    except (ValueError, KeyError, TypeError):
        raise SceneError(f"fidelity {fidelity!r} is not preview, standard, reference or "
                         "'xi=N,theta=N,phi=N,side=N,grid=WxH|none,cells=N' (cells 2..128)") from None


@dataclass
class Components:
    """Radiance components [W sr⁻¹ m⁻²] before the analyzer, each (h, w), or (n,) for requested pixels.

    D direct (eq. 11), A surface-scattered (eq. 12), B backscatter (eq. 13), Bq/Bu the backscatter's
    B-weighted linear Stokes in the camera frame (angles from image right toward image up) and Bv its
    circular Stokes (docs/physics.md §5.1), so p and χ follow; ``surface`` says which pixels see which
    object and the chart's bars. Sq/Su: the object light's linear Stokes in the camera frame, 0 but behind a
    camera port with Fresnel faces, whose diattenuation polarizes the object's light (docs/physics.md §11).
    Bv, Sq, Su not given are a shared read-only array of zeros (:func:`polarstripe.heap.shared_zeros`).
    """

    D: np.ndarray
    A: np.ndarray
    B: np.ndarray
    Bq: np.ndarray
    Bu: np.ndarray
    surface: SurfaceInfo
    scene: Scene
    pattern: PatternSpec
    fidelity: Fidelity
    pixels: np.ndarray | None = None
    seconds: float = 0.0
    orders: OrdersPlan | None = None
    Bv: np.ndarray | None = None
    Sq: np.ndarray | None = None
    Su: np.ndarray | None = None

    def __post_init__(self):      # a field not given is 0: one read-only array of zeros, shared
        for name in ("Bv", "Sq", "Su"):
            if getattr(self, name) is None:
                setattr(self, name, shared_zeros(self.B.shape))

    @property
    def S(self) -> np.ndarray:
        """Object signal S = D + A."""
        return self.D + self.A

    def seen_stokes(self) -> tuple[np.ndarray, np.ndarray]:
        """The backscatter's Stokes on the analyzer's circle (docs/physics.md §5.1): (Bq, Bu) without a
        quarter-wave plate; with one at α, (Q_α cos 2α − V sin 2α, Q_α sin 2α + V cos 2α) with
        Q_α = Bq cos 2α + Bu sin 2α, so that Malus's law in p and χ holds for the rotating analyzer."""
        return self._on_analyzer_circle(self.Bq, self.Bu, self.Bv)

    def object_seen_stokes(self) -> tuple[np.ndarray, np.ndarray]:
        """The object light's (Sq, Su) on the analyzer's circle, as :meth:`seen_stokes` (its V is 0)."""
        return self._on_analyzer_circle(self.Sq, self.Su, 0.0)

    def _on_analyzer_circle(self, q, u, v):
        qw = self.scene.camera.polarizer.quarter_wave_deg
        if qw is None:
            return q, u
        a2 = 2.0 * np.radians(qw)
        q_a = q * np.cos(a2) + u * np.sin(a2)
        return q_a * np.cos(a2) - v * np.sin(a2), q_a * np.sin(a2) + v * np.cos(a2)

    @property
    def p(self) -> np.ndarray:
        """Per-pixel backscatter DOP as the scene's analyzer sees it (B-weighted over the ray; 0 where
        B = 0): the linear DOP, or with a quarter-wave plate at α √(Q_α² + V²)/B (docs/physics.md §5.1)."""
        q, u = self.seen_stokes()
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.B > 0, np.clip(np.hypot(q, u) / self.B, 0.0, 1.0), 0.0)

    @property
    def chi_rad(self) -> np.ndarray:
        """Per-pixel analyzer angle [rad, camera frame] that passes the most backscatter: the angle of its
        linear polarization, or with a plate at α, α + ½ atan2(V, Q_α)."""
        q, u = self.seen_stokes()
        return 0.5 * np.arctan2(u, q)

    @property
    def dolp(self) -> np.ndarray:
        """Per-pixel linear DOP √(Bq² + Bu²)/B of the backscatter (0 where B = 0)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.B > 0, np.clip(np.hypot(self.Bq, self.Bu) / self.B, 0.0, 1.0), 0.0)

    @property
    def v(self) -> np.ndarray:
        """Per-pixel circular polarization V/B of the backscatter, signed (0 where B = 0)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.B > 0, np.clip(self.Bv / self.B, -1.0, 1.0), 0.0)

    @property
    def object_mask(self) -> np.ndarray:
        """True where the pixel sees an object."""
        return self.surface.object_id >= 0

    def combine(self, other: Components, a: float, b: float) -> Components:
        """Linear combination a·self + b·other of the radiance fields (same pixels)."""
        return Components(a * self.D + b * other.D, a * self.A + b * other.A, a * self.B + b * other.B,
                          a * self.Bq + b * other.Bq, a * self.Bu + b * other.Bu, self.surface, self.scene,
                          self.pattern, self.fidelity, self.pixels, self.seconds + other.seconds, self.orders,
                          a * self.Bv + b * other.Bv, a * self.Sq + b * other.Sq, a * self.Su + b * other.Su)


def render_components(scene: Scene, pattern: str | PatternSpec, fidelity: str | Fidelity = "standard",
                      pixels: np.ndarray | None = None,
                      need: tuple[str, ...] = ("D", "A", "B", "p"), orders: str = "all") -> Components:
    """Radiance components of one pattern (paper eqs. 11–13, physical form; docs/physics.md §0, §10).

    Parameters
    ----------
    scene : Scene
    pattern : ``flood``, ``stripe:K/N`` (``stripe:I/N:xS``: S sheets at once), ``checker:SIZE:SHIFT`` or a
        :class:`PatternSpec`.
    fidelity : ``preview`` | ``standard`` | ``reference`` | :class:`Fidelity` |
        ``"xi=..,theta=..,phi=..,grid=.."``.
    pixels : optional (n, 2) int array of (row, col): compute only these (cost scales with n; A exact there).
    need : components to compute (others are zeros): any of ``D``, ``A``, ``B`` and ``p`` (the backscatter
        polarization; without it Bq = Bu = 0, which saves ~40 % of the B cost).
    orders : ``all`` (default): every order of scattering where the scene needs them (decided from its
        optical thickness, albedo and phase function; :mod:`polarstripe.sim.orders`); ``single``: the
        paper's single-scattering model, bit-identical to the renderer before the higher orders.

    Returns
    -------
    Components with arrays of shape (h, w), or (n,) when ``pixels`` is given; ``orders`` says what was
    modelled and the error to expect.
    """
    return answer(component_steps(scene, pattern, fidelity, pixels, need, orders))


def component_steps(scene: Scene, pattern: str | PatternSpec, fidelity: str | Fidelity = "standard",
                    pixels: np.ndarray | None = None, need: tuple[str, ...] = ("D", "A", "B", "p"),
                    orders: str = "all"):
    """:func:`render_components` as steps that yield the frame's grid solves
    (:class:`~polarstripe.sim.multiple.GridSolve`) and return its :class:`Components`
    (:func:`polarstripe.sim.scan_render.render_scan` steps a scan's frames together)."""
    t_start = time.perf_counter()
    if not isinstance(scene, Scene):
        raise SceneError(f"scene must be a Scene (see load_scene), got {type(scene).__name__}")
    pat = parse_pattern(pattern)
    fid = resolve_fidelity(fidelity)
    if not isinstance(need, (tuple, list, set, frozenset)) or not set(need) <= {"D", "A", "B", "p"}:
        raise SceneError(f"need must name components among D, A, B, p, got {need!r}")
    plan = plan_orders(scene, orders, fid.name)
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
        on = yield from component_steps(clean, pat, fid, pixels, need, orders)
        flood = yield from component_steps(clean, "flood", fid, pixels, need, orders)
        out = on.combine(flood, 1.0 - black, black)
        out.scene, out.seconds = scene, time.perf_counter() - t_start
        return out
    src = make_source(scene, pat)
    if has_port(scene):      # refraction at flat ports (docs/physics.md §11)
        *parts, surf = port_parts(scene, src, fid, cam, pixels, need, plan)
        shape = (cam.h, cam.w) if pixels is None else (-1,)
        surf = SurfaceInfo(*(a.reshape(shape) for a in (surf.object_id, surf.albedo, surf.chart_band,
                                                         surf.chart_high)))
        D, A, B, Bq, Bu, Bv, Sq, Su = (a.reshape(shape) for a in parts)
        return Components(D, A, B, Bq, Bu, surf, scene, pat, fid, pixels, time.perf_counter() - t_start, plan,
                          Bv, Sq, Su)
    if pixels is None:        # the camera's geometry, once for every projector pose (sim/geometry_cache.py)
        dirs, hits, surf = cached(camera_only(scene), "camera", lambda: _camera_geometry(scene, cam, None))
    else:
        dirs, hits, surf = _camera_geometry(scene, cam, pixels)
    n = dirs.shape[0]
    view = View(scene, pat, fid, cam, dirs, hits, surf, pixels)
    if plan.modelled:
        D, A, B, Bq, Bu, Bv = yield from higher_steps(view, src, plan, need, fid.higher)
    else:
        D, A, B, Bq, Bu, Bv = single_parts(view, src, need)
    shape = (cam.h, cam.w) if pixels is None else (n,)
    surf = SurfaceInfo(*(a.reshape(shape) for a in (surf.object_id, surf.albedo, surf.chart_band,
                                                     surf.chart_high)))
    D, A, B, Bq, Bu, Bv = (a.reshape(shape) for a in (D, A, B, Bq, Bu, Bv))
    return Components(D, A, B, Bq, Bu, surf, scene, pat, fid, pixels, time.perf_counter() - t_start, plan, Bv)


def render_each(scene: Scene, patterns, fidelity: str | Fidelity = "standard", **kwargs) -> list[Components]:
    """:func:`render_components` of each of ``patterns`` (same keyword arguments), rendered together:
    :func:`polarstripe.sim.scan_render.render_scan` (the frames' grid solves batched, chunks of the scan in
    parallel on the model's threads); the same as one after another, to the bit."""
    from polarstripe.sim.scan_render import render_scan  # (that module builds on this one)

    return render_scan(scene, patterns, fidelity, **kwargs)


def _camera_geometry(scene: Scene, cam, pixels):
    """The camera's ray directions, their hits and the surface under each (flat)."""
    dirs = pixel_rays(cam, pixels)
    hits = intersect(scene.objects, cam.position, dirs)
    return dirs, hits, surface_info(scene.objects, hits)


def render_frame(scene: Scene, pattern: str | PatternSpec, polarizer_deg: float | None = None,
                 fidelity: str | Fidelity = "standard", seed: int | np.random.Generator | None = None,
                 pixels: np.ndarray | None = None, orders: str = "all"):
    """One simulated camera frame: components → analyzer (Malus) → EMVA 1288 sensor.

    Returns
    -------
    (dn, components): dn uint16 (h, w) digital numbers (``bits``-bit, clipped), and the Components.
    ``seed`` None uses ``camera.seed``.
    """

    comp = render_components(scene, pattern, fidelity, pixels, orders=orders)
    radiance = analyzer(comp, polarizer_deg)
    rng = scene.camera.seed if seed is None else seed
    return expose(radiance, scene.camera, rng, pixels=pixels), comp
