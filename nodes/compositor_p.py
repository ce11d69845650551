"""The compositor's medium model for eq. 6's p (:mod:`polarstripe.nodes.compositor`, docs/physics.md §4.2).

With ``p_rule = "map"`` eq. 6 divides by the DOP the analyzer pair sees at each pixel. Where the compositor
knows a medium, the map is the model's (:func:`~polarstripe.planning.medium_p.p_map_with_model`): the scene
of the ``p_scene`` param (``""`` the paper's tank, as the planner's) with the rig's optics (``light``), its
medium replaced by the estimator's fit (``medium/estimate``, σ_t and the mean cosine) once one comes, at the
source's pose: the scan's ``simulator/truth`` (``separation_m``), else the last ``planner/plan``, else the
scene's. The model's scale κ and the analyzer's angle ψ (:func:`~polarstripe.planning.medium_p.fit_pair`)
are fitted to the last polarized flood pair at the scan's pose (kept, and fitted again with the medium known
at each scan): the flood model does not predict the object light in a stripe composite (fitted to one, at
the demo's pose, p read 0.42 where the flood's read 0.51, the truth's); a stripe scan without a polarized
flood before it at its pose is fitted to its own composites, and its metrics' ``p_note`` says so.
``p_scene = "none"``: no model, the map comes from the frames alone
(:func:`~polarstripe.imaging.p_map.regional_p_map`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from polarstripe.imaging.p_map import PEstimate
from polarstripe.imaging.validation import roi_slices
from polarstripe.msgs import Composite, MediumEstimate, Method, Plan
from polarstripe.planning.medium_p import fit_pair, p_map_with_model
from polarstripe.sim.render import render_components, resolve_fidelity
from polarstripe.sim.scene import Phase, Scene, load_scene, with_light, with_separation

CACHED = 4  # model renders kept (one per pose, medium and frame size)


class MediumModel:
    """The medium the compositor's ``map`` rule reads eq. 6's p from (module docstring)."""

    def __init__(self, params):
        self.rule, self.fidelity = params.p_rule, resolve_fidelity(params.p_fidelity)
        self.base: Scene | None = None
        if params.p_scene != "none":
            scene = load_scene(params.p_scene or None)
            self.base = scene if params.light == "scene" else with_light(scene, params.light)
        self.plan_sep: float | None = None
        self.fitted: tuple[float, float] | None = None  # (σ_t, g) of the last estimate that had them
        self._renders: dict[tuple, object] = {}
        self._flood: tuple | None = None  # the last polarized flood's (pose, pair, region, dark, saturation)

    def warm(self) -> None:
        """Load the model's kernels now (numba's cache: seconds in a fresh process), in the node's setup,
        not in the first polarized scan's composite."""
        if self.rule == "map" and self.base is not None:
            render_components(self.base.replace(camera=self.base.camera.resized((8, 6))), "flood",
                              self.fidelity)

    def on_plan(self, plan: Plan) -> None:
        self.plan_sep = float(plan.separation_m)

    def on_estimate(self, est: MediumEstimate) -> None:
        if not est.reason and est.sigma_t_per_m is not None and est.mean_cosine is not None:
            self.fitted = (float(est.sigma_t_per_m), float(est.mean_cosine))

    def scene(self, truth: Composite | None) -> Scene | None:
        """The model's scene at the scan's pose with the medium known now; None without a model."""
        if self.base is None:
            return None
        sep = truth.metrics.get("separation_m") if truth is not None else None
        sep = self.plan_sep if sep is None else float(sep)
        scene = self.base if sep is None or not math.isfinite(sep) else with_separation(self.base, sep)
        if self.fitted is not None:
            sigma_t, g = self.fitted
            scene = scene.replace(medium=scene.medium.replace(sigma_t=sigma_t, phase=Phase("tthg", g)))
        return scene

    def p_model(self, method: str, truth: Composite | None, object_free, dark: float,
                saturation: float | None, p_min: float, crossed: bool = False):
        """The callable :func:`~polarstripe.imaging.compose.compose` takes as ``p_model`` for a scan of
        ``method``, or None (another rule, or no model); ``crossed``: its pair is crossed at each pixel's
        own angle (a polarization camera's ``local`` or ``pixel`` rule)."""
        scene = self.scene(truth)
        if self.rule != "map" or scene is None:
            return None

        def p_map(e_b: np.ndarray, e_w: np.ndarray) -> PEstimate:
            h, w = e_b.shape
            sc = scene.replace(camera=scene.camera.replace(resolution=(w, h)))
            region = np.ones((h, w), bool)
            if object_free is not None:
                region[:] = False
                region[roi_slices("object_free", object_free, (h, w))] = True
            sat = math.inf if saturation is None else saturation
            comps, pose, note = self._render(sc), (w, h, sc.projector.position), ""
            if Method(method).family == "flood":
                self._flood = (pose, (e_b, e_w), region, dark, sat)
            flood = self._flood if self._flood is not None and self._flood[0] == pose else None
            fit = fit_pair(comps, *(flood[1:] if flood is not None else ((e_b, e_w), region, dark, sat)),
                           crossed=crossed)
            if flood is None and not isinstance(fit, str):
                note = "κ fitted to the stripe composites (no polarized flood at this pose): p reads low"
            est = p_map_with_model((e_b, e_w), region, dark, sat, sc, self.fidelity.name, p_min=p_min,
                                   components=comps, fit=None if isinstance(fit, str) else fit,
                                   crossed=crossed)
            return est if est.note or not note else dataclasses.replace(est, note=note)

        return p_map

    def _render(self, scene: Scene):
        """The model's flood components of ``scene``, from the last few renders when it is one of them."""
        key = (scene.camera.resolution, scene.projector.position, scene.medium.sigma_t,
               repr(scene.medium.phase))
        if key not in self._renders:
            while len(self._renders) >= CACHED:
                del self._renders[next(iter(self._renders))]
            self._renders[key] = render_components(scene, "flood", self.fidelity)
        return self._renders[key]
