"""The planner's model of a rig: light-transport components at the observed points only (never whole images).

:class:`SceneModel` evaluates :func:`polarstripe.sim.render.render_components` at a few pixels per
separation. Flood: one call for all observed points. Stripes (docs/planning.md §1): per observed point O_i
one call for its own sheet, centred on O_i, evaluated at O_i and at its unlit neighbours O′ (left and
right); with ``edge="margin"`` also one call per other sheet of the scan that crosses an observed ray,
evaluated at the observed points only (B and its DOP: these sheets reach O through its ray, not through
its surface).
"""

from __future__ import annotations

import math

import numpy as np
from polarstripe.planning.objectives import EDGES, Competitors, Samples, SensorNoise
from polarstripe.sim.geometry import box_interval, intersect, pinhole_frame, pixel_rays, projector_coords
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import Box, PlaneObject, Scene, SceneError, with_separation
from polarstripe.sim.sensor import electrons_per_radiance

NEIGHBOUR, SHEET = "neighbour", "sheet"


def fig8_scene(sigma_t: float = 6.0, projector: str = "point", half_width_m: float = 1.0) -> Scene:
    """The paper's Fig. 8 simulation: the default camera, an isotropic point source (``projector="point"``,
    flood only; ``"pinhole"`` for stripes) on the front facade, a Lambertian plane of albedo 0.6 at
    z = 0.38 m (no texture, unbounded), and a medium of extinction ``sigma_t`` [1/m] whose front facade
    extends ``half_width_m`` either side of the camera, past every separation swept."""
    base = Scene()
    extent = Box((-half_width_m, -half_width_m, 0.0), (half_width_m, half_width_m, 0.38), key="medium.extent")
    return base.replace(medium=base.medium.replace(sigma_t=sigma_t, extent=extent),
                        projector=base.projector.replace(model=projector),
                        objects=(PlaneObject(point=(0.0, 0.0, 0.38), normal=(0.0, 0.0, -1.0), albedo=0.6),))


def part_frame(part):
    """The pinhole frame of a scene's camera or projector."""
    return pinhole_frame(part.position, part.look_at, part.up, part.fov_deg, part.resolution)


class SceneModel:
    """The planner's model (:class:`~polarstripe.planning.planner.PlanModel`) on :mod:`polarstripe.sim`.

    Parameters
    ----------
    scene : Scene
        The rig; the projector is moved along the front face by :func:`~polarstripe.sim.scene.with_separation`
        and kept aimed at its look-at point.
    fidelity : str
        Model fidelity (``preview``, ``standard``, ``reference`` or explicit counts).
    n_stripes : int
        Stripes per scan: the angular width of a sheet is 1/N of the projector's field of view, and the scan's
        other sheets are the projector's N stripes.
    pixels : (n, 2) int array, optional
        Observed points O_i (row, col). Default: three points on the centre row at 1/4, 1/2 and 3/4 of the
        width (the stripe locations O1, O2, O3 of the paper's Fig. 10); each must see an object.
    edge : {"margin", "eq9"}
        The stripe measure (:mod:`~polarstripe.planning.objectives`): ``margin`` evaluates the competitors
        (about 15–25 cheap calls per separation), ``eq9`` only O under its own sheet.
    """

    def __init__(self, scene, fidelity: str = "standard", n_stripes: int = 30, pixels=None,
                 edge: str = "margin", orders: str = "all"):
        if orders not in ("single", "all"):
            raise SceneError(f"orders must be 'single' or 'all', got {orders!r}")
        # "all": the orders the scene needs, as the simulator renders (sim/orders.py); "single": the paper's
        # model. Plans are judged end to end by planning/validate_table.py (docs/planning.md §7)
        self.orders = orders
        if edge not in EDGES:
            raise SceneError(f"edge must be one of {EDGES}, got {edge!r}")
        if isinstance(n_stripes, bool) or int(n_stripes) != n_stripes or n_stripes < 1:
            raise SceneError(f"n_stripes must be a positive integer, got {n_stripes!r}")
        cam = scene.camera
        w, h = cam.resolution
        if pixels is None:
            pixels = [[h // 2, int(w * f)] for f in (0.25, 0.5, 0.75)]
        self.pixels = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
        self.scene, self.fidelity, self.n_stripes, self.edge = scene, fidelity, int(n_stripes), edge
        self._cam = part_frame(cam)
        self._dirs = pixel_rays(self._cam, self.pixels)
        hits = intersect(scene.objects, self._cam.position, self._dirs)
        if not np.all(np.isfinite(hits.t)):
            bad = self.pixels[~np.isfinite(hits.t)].tolist()
            raise SceneError(f"planner pixels {bad} see no object: observed points must lie on an object")
        self.points, self._t_hit = hits.point, hits.t
        lo, hi = scene.medium.extent.min, scene.medium.extent.max
        self._t_entry = np.minimum(box_interval(self._cam.position, self._dirs, lo, hi)[0], self._t_hit)
        axis = np.subtract(with_separation(scene, 1.0).projector.position, cam.position)
        self._lateral = (self.points - np.asarray(cam.position)) @ (axis / np.linalg.norm(axis))
        # pixel boundaries j - 1/2 (j = 0..w) along each observed row: where the neighbours O' are sought
        cols = np.arange(w + 1, dtype=float) - 0.5
        self._edges = []
        for row in self.pixels[:, 0]:
            bh = intersect(scene.objects, self._cam.position,
                           pixel_rays(self._cam, np.stack([np.full(w + 1, float(row)), cols], axis=1)))
            self._edges.append((bh.point, np.isfinite(bh.t)))
        gain = cam.gain_e_per_dn
        self.noise = SensorNoise(electrons_per_radiance(cam, self.pixels), cam.read_noise_e,
                                 cam.dark_current_e_s * cam.exposure_s, gain / math.sqrt(12.0),
                                 min(cam.full_well_e, ((1 << cam.bits) - 1 - cam.offset_dn) * gain))

    def observed_pixels(self) -> np.ndarray:
        return self.pixels

    def lateral_positions_m(self) -> np.ndarray:
        """Position of each O_i along the direction the source moves [m], from the camera."""
        return self._lateral

    def _at(self, d_lc_m: float):
        return with_separation(self.scene, d_lc_m, aim=True)

    def flood(self, d_lc_m: float) -> Samples:
        c = render_components(self._at(d_lc_m), "flood", self.fidelity, self.pixels, orders=self.orders)
        return Samples(c.D, c.A, c.B, c.p)

    def stripes(self, d_lc_m: float) -> Samples:
        """Components at each O_i under its own sheet and, with ``edge="margin"``, its competitors.

        O_i's own sheet has the angular width of one of ``n_stripes`` stripes and passes through the source
        and O_i (the paper's Fig. 8c): the projector is aimed at O_i and narrowed to three columns of that
        width, the middle one lit, so O_i sits at its stripe's centre at every separation and the curves do
        not jitter with where a fixed projector's stripe edges fall. The neighbours O′ are the nearest pixels
        on O_i's row, left and right, whose whole footprint lies outside that sheet; their D and A are scaled
        by ρ(O)/ρ(O′) (both are proportional to the albedo at the point), so a texture edge is not read as a
        stripe edge. The other sheets are the projector's N stripes from the same source position (the
        rotate scan), except the one containing O_i.
        """
        sd = self._at(d_lc_m)
        base = sd.projector
        tan_half = math.tan(math.radians(base.fov_deg) / 2.0)
        pitch = 2.0 * tan_half / self.n_stripes  # one stripe's width, tan units
        rows = max(3, round(base.resolution[1] * 2.0 * tan_half / base.resolution[0] / pitch))
        fov = math.degrees(2.0 * math.atan(1.5 * pitch))
        n = len(self.pixels)
        own = np.zeros((4, n))
        nb = np.zeros((4, n, 2))
        margin = self.edge == "margin"
        for i, point in enumerate(self.points):
            proj = base.replace(look_at=tuple(float(v) for v in point), resolution=(3, rows), fov_deg=fov)
            pix = [self.pixels[i]]
            sides = self._neighbours(part_frame(proj), i) if margin else []
            pix += [p for _, p in sides]
            c = render_components(sd.replace(projector=proj), "stripe:1/3", self.fidelity, np.array(pix),
                                  orders=self.orders)
            own[:, i] = c.D[0], c.A[0], c.B[0], c.p[0]
            rho = c.surface.albedo
            for k, (side, _) in enumerate(sides, start=1):
                scale = rho[0] / rho[k] if rho[k] > 0 else 0.0
                nb[:, i, side] = c.D[k] * scale, c.A[k] * scale, c.B[k], c.p[k]
        if not margin:
            return Samples(*own)
        sheets = self._other_sheets(sd)
        comp = Competitors(*(np.concatenate([nb[j], sheets[j]], axis=1) for j in range(4)),
                           labels=(NEIGHBOUR, NEIGHBOUR) + (SHEET,) * self.n_stripes)
        return Samples(*own, competitors=comp)

    def _neighbours(self, sheet_frame, i: int) -> list[tuple[int, list[int]]]:
        """[(side, [row, col])] of O_i's unlit neighbours: side 0 the nearest pixel to the left, 1 to the
        right, whose boundary facing the stripe lies outside the lit middle column [1, 2) of the sheet's
        frame (or sees no object); a side with no such pixel in the image is left out."""
        row, col = (int(v) for v in self.pixels[i])
        points, hit = self._edges[i]
        kappa = np.full(hit.shape, np.nan)
        kappa[hit] = projector_coords(sheet_frame, points[hit])[0]
        outside = ~((kappa >= 1.0) & (kappa < 2.0))  # NaN (no object) is outside
        out = []
        left = np.nonzero(outside[1:col + 1])[0]  # boundary j + 1 is the right edge of pixel j
        if left.size:
            out.append((0, [row, int(left[-1])]))
        right = np.nonzero(outside[col + 1:-1])[0]  # boundary j is the left edge of pixel j
        if right.size:
            out.append((1, [row, col + 1 + int(right[0])]))
        return out

    def _other_sheets(self, sd) -> np.ndarray:
        """(4, n, N) D, A, B, p at each O_i under each stripe k of the projector at this separation: B and
        its DOP for the stripes whose sheet crosses O_i's ray in the medium (D = A = 0: O_i lies outside
        them; their A at O_i is below the neighbour's, which is nearer the lit sheet), zeros for O_i's own
        stripe and for stripes that miss the ray."""
        n, big_n = len(self.pixels), self.n_stripes
        out = np.zeros((4, n, big_n))
        frame = part_frame(sd.projector)
        edges = (np.arange(big_n + 1) * frame.w) // big_n
        start = self._cam.position + self._t_entry[:, None] * self._dirs
        k0, _, dep0 = projector_coords(frame, start)
        k1, _, dep1 = projector_coords(frame, self.points)
        need = np.zeros((n, big_n), bool)
        for i in range(n):
            own = int(np.searchsorted(edges, k1[i], side="right")) - 1
            if dep0[i] > 0 and dep1[i] > 0:  # the column coordinate is monotone along the ray
                lo, hi = min(k0[i], k1[i]), max(k0[i], k1[i])
                need[i] = (edges[1:] > lo) & (edges[:-1] <= hi)
            else:
                need[i] = True
            if 0 <= own < big_n:
                need[i, own] = False
        for k in np.nonzero(need.any(axis=0))[0]:
            idx = np.nonzero(need[:, k])[0]
            c = render_components(sd, f"stripe:{k}/{big_n}", self.fidelity, self.pixels[idx],
                                  need=("B", "p"), orders=self.orders)
            out[2, idx, k], out[3, idx, k] = c.B, c.p
        return out
