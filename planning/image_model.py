"""The planner's model for the ``error`` measure: a low-resolution render of the whole image per separation.

:class:`ImageModel` serves :func:`polarstripe.planning.planner.plan` like
:class:`~polarstripe.planning.scene_model.SceneModel`, but instead of a few observed points it renders the
components of the whole frame at a low resolution (``width`` pixels, the exposure scaled by the pixel's
solid angle so each pixel collects the electrons of the scene camera's), with every order of scattering as
the scene needs (:mod:`polarstripe.sim.orders`), and T, the unscattered object radiance the composite is
scored against (docs/physics.md §10.8). Values are electrons at the scene's exposure (its ``noise`` converts
with 1), so :func:`~polarstripe.planning.planner.auto_exposure_scale` and the full well apply as they are.

The renders are as wide as the scene's camera, at most ``PX_PER_STRIPE`` pixels per stripe, unless ``width``
says otherwise: a 30-stripe composite at a few pixels per stripe aliases on the camera's pixel grid, and its
error with it; at 10 pixels per stripe that is small, and a wider render costs time for nothing
(docs/planning.md §8).

* flood: one flood frame; one location (group 0).
* stripes: the scan's frames (the projector aimed as the rig aims it, N stripes, ``sheets`` per frame:
  ⌈N/K⌉ frames ``stripe:I/N:xK`` carrying the backscatter of K sheets each; every ``stripe_step``-th
  with a step > 1, and then only the pixels they light or that see no object), composed by eq. 7 as the
  compositor does; one location per observed point, the pixels nearest its column. The flood frame's
  backscatter DOP and angle come along: the analyzer is calibrated on the flood, and eq. 6's ``map`` rule
  (``p_rule``, the compositor's default) divides a stripe composite by the flood's map.

:mod:`polarstripe.planning.predicted_error` turns these into the expected error of each reading.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from polarstripe.msgs.patterns import stripes
from polarstripe.planning.medium_p import p_map_with_model
from polarstripe.planning.objectives import Samples, SensorNoise
from polarstripe.planning.predicted_error import P_RULES, mean_angle, polarized_frames
from polarstripe.planning.scene_model import part_frame
from polarstripe.sim.geometry import intersect, pixel_rays
from polarstripe.sim.higher import HigherSettings
from polarstripe.sim.render import Fidelity, render_components, resolve_fidelity
from polarstripe.sim.scan_render import render_scan
from polarstripe.sim.scene import Scene, SceneError, with_separation
from polarstripe.sim.sensor import electrons_per_radiance, full_scale_dn, mean_dn
from polarstripe.sim.truth import unscattered_object

# the default renders' resolution: the camera's, but no finer than this many pixels per stripe (at 10 a
# stripe composite's aliasing is small; docs/planning.md §8)
PX_PER_STRIPE = 10
MAP_FIDELITY = "preview"   # the compositor's p map is rendered at this level (nodes/compositor_params.py)
# a scan's grid solves in low rank (sim/multiple.py propagate): the orders' light within ~1e-4 of its peak of
# the frame-by-frame solve, a fifth off a `standard` scan (docs/planning.md §8, "A scan rendered together")
SCAN_RANK_TOL = 1e-3
FLOOD_MAPS_KEPT = 64    # separations whose flood map is kept: a coarse plan's floods (~40); 1.6 MB each at
                        # the default 300 × 225 px
OWN_MAP = (MAP_FIDELITY, "draft")   # levels that divide by their own flood's DOP (draft: the map's preview
                                    # render would make it dearer than preview, 34-37 s against 19-25 a plan)

# the planner's own level below the simulator's preview (docs/planning.md §8, the ladder): the higher orders
# on a grid of 8 cells along the tank, 2 orders and one of the glow, the single-scattering backscatter at a
# quarter of the resolution, fewer quadrature nodes; the picks it gives are judged end to end by
# `polarstripe bench planner` (regret per scene), not its pixels
PLAN_FIDELITY = {
    "draft": Fidelity("draft", 3, 2, 6, (8, 4), 3,
                      HigherSettings(cells=8, orders=2, glow_orders=1, view_div=16, view_steps=12,
                                     patch_cells=2.0, glow_dirs=12, oversample=0.5, b_div=4,
                                     a1_exact=False, half_res=True)),
}


def plan_fidelity(fidelity: str | Fidelity) -> Fidelity:
    """The planner's fidelity: ``draft`` (:data:`PLAN_FIDELITY`) or any of the simulator's
    (:func:`polarstripe.sim.render.resolve_fidelity`; a bad name is one error naming them)."""
    if isinstance(fidelity, str) and fidelity in PLAN_FIDELITY:
        return PLAN_FIDELITY[fidelity]
    try:
        return resolve_fidelity(fidelity)
    except SceneError:
        raise SceneError(f"fidelity {fidelity!r} is not preview, standard, reference, draft (the planner's) "
                         "or 'xi=N,theta=N,phi=N,side=N,grid=WxH|none,cells=N'") from None


class ImageModel:
    """Whole low-resolution frames per separation (module docstring).

    Parameters
    ----------
    scene : Scene
    fidelity : model fidelity of the renders (``preview`` by default: the measure compares separations,
        and `bench planner` shows what the level costs in regret), or the planner's ``draft``
        (:data:`PLAN_FIDELITY`).
    n_stripes : stripes per scan.
    width : width [px] of the renders; None (default): the scene camera's, whose pixel grid the stripe
        composite aliases on, up to ``PX_PER_STRIPE`` px per stripe; at least 3 px per stripe, at most the
        camera's (the height keeps the aspect, at least 8).
    fractions : where the observed points sit on the centre row (fractions of the width): their stripes
        are the stripe locations.
    orders : ``all`` (as the scene needs) or ``single``.
    sheets : light sheets per stripe frame (msgs/patterns.py ``stripe:I/N:xK``).
    p_rule : eq. 6's p the composite is predicted with (planning/predicted_error.py): ``map`` (the
        compositor's default, the model's DOP per pixel) or ``median`` (one p̂).
    """

    measure = "error"
    edge = "margin"

    def __init__(self, scene: Scene, fidelity: str = "preview", n_stripes: int = 30,
                 width: int | None = None, fractions=(0.25, 0.5, 0.75), orders: str = "all",
                 stripe_step: int = 1, sheets: int = 1, p_rule: str = "map"):
        if p_rule not in P_RULES:
            raise SceneError(f"p_rule must be one of {', '.join(P_RULES)}, got {p_rule!r}")
        self.p_rule = p_rule
        if orders not in ("single", "all"):
            raise SceneError(f"orders must be 'single' or 'all', got {orders!r}")
        if isinstance(n_stripes, bool) or int(n_stripes) != n_stripes or n_stripes < 1:
            raise SceneError(f"n_stripes must be a positive integer, got {n_stripes!r}")
        w0, h0 = scene.camera.resolution
        if width is None:  # the camera's grid where a stripe spans few of its pixels (aliasing), else cheaper
            width = min(w0, PX_PER_STRIPE * int(n_stripes))
        elif isinstance(width, bool) or int(width) != width or int(width) < 8:
            raise SceneError(f"width must be an integer of at least 8 pixels, got {width!r}")
        # a stripe at least 3 pixels wide: narrower, which pixels a stripe lights jumps with the separation
        # and the stripe curves with it (bench planner --end-to-end: the same pick on every scene at 48 px)
        w = min(max(int(width), 3 * int(n_stripes)), w0)
        h = max(8, round(w * h0 / w0))
        cam = scene.camera.replace(resolution=(w, h), exposure_s=scene.camera.exposure_s * (w / w0) ** 2)
        self.scene = scene.replace(camera=cam)
        if isinstance(stripe_step, bool) or int(stripe_step) != stripe_step or not 1 <= stripe_step:
            raise SceneError(f"stripe_step must be a positive integer, got {stripe_step!r}")
        self.fidelity, self.n_stripes, self.orders = plan_fidelity(fidelity), int(n_stripes), orders
        self.stripe_step = int(stripe_step)
        if isinstance(sheets, bool) or int(sheets) != sheets or not 1 <= sheets <= n_stripes:
            raise SceneError(f"sheets must be an integer 1..n_stripes ({n_stripes}), got {sheets!r}")
        self.sheets = int(sheets)
        self.shape = (h, w)
        self._e = electrons_per_radiance(cam).reshape(-1)
        frame = part_frame(cam)
        self.pixels = np.array([[h // 2, min(w - 1, int(w * f))] for f in fractions], np.int64)
        dirs = pixel_rays(frame, self.pixels)
        hits = intersect(scene.objects, frame.position, dirs)
        if not np.all(np.isfinite(hits.t)):
            raise SceneError(f"planner pixels {self.pixels[~np.isfinite(hits.t)].tolist()} see no object")
        self._points = hits.point
        cols = np.tile(np.arange(w), h)
        self._columns = np.argmin(np.abs(cols[:, None] - self.pixels[None, :, 1]), axis=1)
        axis = np.subtract(with_separation(scene, 1.0).projector.position, cam.position)
        self._lateral = (self._points - np.asarray(cam.position)) @ (axis / np.linalg.norm(axis))
        gain = cam.gain_e_per_dn
        self.noise = SensorNoise(1.0, cam.read_noise_e, cam.dark_current_e_s * cam.exposure_s,
                                 gain / np.sqrt(12.0),
                                 min(cam.full_well_e, ((1 << cam.bits) - 1 - cam.offset_dn) * gain))
        self._flood_maps: dict[float, tuple] = {}    # separation → the flood's map a stripe scan divides by

    def observed_pixels(self) -> np.ndarray:
        return self.pixels

    def lateral_positions_m(self) -> np.ndarray:
        return self._lateral

    def _render(self, scene: Scene, pattern: str):
        return _parts(render_components(scene, pattern, self.fidelity, orders=self.orders))

    def _samples(self, truth, parts, keep, group) -> Samples:
        d, s, b, p, chi = (x[keep] for x in parts)
        e = self._e[keep]
        return Samples(d * e, (s - d) * e, b * e, p, chi=chi, truth=truth[keep] * e, group=group,
                       p_rule=self.p_rule)

    def flood(self, d_lc_m: float) -> Samples:
        sd = with_separation(self.scene, d_lc_m, aim=True)
        parts = self._render(sd, "flood")
        keep = np.ones(parts[0].size, bool)
        truth = unscattered_object(sd)[0].reshape(-1)
        samples = self._samples(truth, parts, keep, np.zeros(keep.size, np.int64))
        flood = self._flood_map(d_lc_m, sd, truth, parts)
        if self.fidelity.name in OWN_MAP:
            return samples                  # the map is the frame's own DOP
        return dataclasses.replace(samples, flood_dop=flood)

    def _flood_map(self, d_lc_m: float, sd: Scene, truth, parts=None) -> tuple:
        """(B_f, p_f, χ_f) a stripe scan at ``d_lc_m`` divides by: the flood frame's own (:data:`OWN_MAP`
        levels) or the compositor's map of it (:meth:`_map`), from the flood's ``parts`` or a render of it.
        Kept per separation (the last :data:`FLOOD_MAPS_KEPT`): a plan evaluates the flood, then the
        stripes, at mostly the same separations."""
        key = float(d_lc_m)
        if key not in self._flood_maps:
            if self.fidelity.name in OWN_MAP and parts is None:
                c = render_components(sd, "flood", self.fidelity, need=("B", "p"), orders=self.orders)
                kept = (c.B.reshape(-1), c.p.reshape(-1), c.chi_rad.reshape(-1))
            elif self.fidelity.name in OWN_MAP:
                kept = parts[2:]
            else:
                kept = self._map(sd, self._render(sd, "flood") if parts is None else parts, truth)
            if len(self._flood_maps) >= FLOOD_MAPS_KEPT:
                self._flood_maps.pop(next(iter(self._flood_maps)))          # the oldest
            self._flood_maps[key] = kept
        return self._flood_maps[key]

    def backscatter_dop(self, d_lc_m: float) -> float:
        """Σ p B / Σ B over a flood frame at ``d_lc_m`` (the mean DOP where B is 0 everywhere): the medium's p
        as an estimate reports it (planning/medium_p.py), from B and its DOP alone."""
        sd = with_separation(self.scene, d_lc_m, aim=True)
        c = render_components(sd, "flood", self.fidelity, need=("B", "p"), orders=self.orders)
        b, p = np.asarray(c.B, np.float64).reshape(-1), np.nan_to_num(np.asarray(c.p, np.float64)).reshape(-1)
        return float(np.sum(b * p) / np.sum(b)) if np.sum(b) > 0 else float(np.mean(p))

    def _map(self, sd: Scene, parts, truth) -> tuple:
        """(B_f, p̂, χ̄) eq. 6's map and the analyzer's axis are read from, as the compositor makes them, for a
        plan at a level finer than the map's (not :data:`OWN_MAP`): the noise-free flood pair through the
        analyzer at the flood's mean angle χ̄, fitted by the compositor's own function (planning/medium_p.py
        ``p_map_with_model``, its model rendered at :data:`MAP_FIDELITY`); p̂ is the DOP that fit says the
        pair sees at each pixel, so χ̂ = χ̄ everywhere. The map's scale comes from the model's B/(S + B) at
        that level, not the plan's: the difference stays in Ŝ, as it does on the rig."""
        _, s, b, p, chi = (np.nan_to_num(np.asarray(x, np.float64)) for x in parts)
        chi_bar = mean_angle(b, p, chi)
        h, w = self.shape
        pair = tuple(x.reshape(h, w) for x in polarized_frames(s, b, p, chi, chi_bar))
        free = (np.asarray(truth) <= 0).reshape(h, w)
        est = p_map_with_model(pair, free if free.any() else None, 0.0, math.inf, sd, MAP_FIDELITY)
        eq6 = np.broadcast_to(np.asarray(est.eq6, np.float64), (h, w)).reshape(-1)
        return b, eq6, np.full(b.size, chi_bar)

    def saturated_fraction(self, d_lc_m: float) -> float:
        """The fraction of a flood frame without analyzer (the brightest frame of any method) at or beyond
        full scale at separation ``d_lc_m`` (:func:`~polarstripe.sim.sensor.mean_dn` of the low-resolution
        camera, whose pixels collect as many electrons as the scene camera's)."""
        sd = with_separation(self.scene, d_lc_m, aim=True)
        c = render_components(sd, "flood", self.fidelity, need=("D", "A", "B"), orders=self.orders)
        return float(np.mean(mean_dn(c.D + c.A + c.B, sd.camera) >= full_scale_dn(sd.camera)))

    def stripes(self, d_lc_m: float) -> Samples:
        """Every ``stripe_step``-th frame of the scan (``sheets`` sheets each), (F, n): the objective composes
        them by eq. 7 at each analyzer angle. Locations: each pixel belongs to the nearest observed point's
        column."""
        sd = with_separation(self.scene, d_lc_m, aim=True)
        truth = unscattered_object(sd)[0].reshape(-1)
        frames = list(stripes(self.n_stripes, self.sheets))[::self.stripe_step]
        comps = render_scan(sd, [str(p) for p in frames], self.fidelity, orders=self.orders,
                            rank_tol=SCAN_RANK_TOL)                                          # together
        parts = [_parts(c) for c in comps]
        flood = self._flood_map(d_lc_m, sd, truth)
        d, s, b, p, chi = (np.stack([x[j] for x in parts]) for j in range(5))
        group = self._columns
        if self.stripe_step > 1:      # pixels lit by a skipped stripe are not composed: left out (−1)
            group = np.where((d > 0).any(axis=0) | (truth <= 0), group, -1)
        return Samples(d * self._e, (s - d) * self._e, b * self._e, p, chi=chi, truth=truth * self._e,
                       group=group, p_rule=self.p_rule, flood_dop=flood)


def _parts(c) -> tuple:
    """(D, S, B, p, χ) of a frame's components, flat."""
    return (c.D.reshape(-1), (c.D + c.A).reshape(-1), c.B.reshape(-1), c.p.reshape(-1), c.chi_rad.reshape(-1))
