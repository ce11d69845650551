"""The planner node: the camera–source placement of the paper's §3 as a service, re-planned in situ.

* serves ``planner/plan`` (``Empty`` → :class:`Plan`): the current plan (computed at start-up); every call
  also publishes it on the topic ``planner/plan`` (the simulator moves its source when a plan arrives);
* publishes ``planner/plan`` once on start-up (``publish_on_start``, after ``publish_delay_s`` so that
  subscribers have joined);
* subscribes ``medium/estimate`` (the estimator node's in-situ fit) and ``compositor/medium_p`` (the
  compositor's p after a polarized method; ignored once a fit has given p): when the measured p differs from
  the p the plan assumed by more than
  ``p_tolerance`` (absolute), σ_t by more than ``sigma_tolerance`` (relative) or the mean cosine by more than
  ``g_tolerance`` (absolute), the scene's medium takes the measured values (a constant DOP p; σ_t and the TTHG
  mean cosine when given, as the in-situ fit of docs/planning.md §6 publishes them; an estimate with a
  ``reason`` carries p only; a NaN p is no p) and the plan is made again and published; after every
  ``medium/estimate`` the plan is published, re-made or not, with ``curves["estimate_scan_id"]`` the scan id
  of the estimate it answers (the sequencer's rescan waits for it); that medium
  is kept in the run directory (``state/planner.json``, runtime/liveness.py), so a respawned planner makes
  the same plan.

The plan comes from :func:`polarstripe.planning.planner.plan` on the model of its ``measure``
(:func:`~polarstripe.planning.planner.plan_model`: ``error``, the composite's expected error against the
unscattered object from low-resolution whole frames, or ``paper``, the paper's measures at three observed
points; ``scene``, ``resolution``, ``fidelity``, ``separations`` between ``d_min_m`` and ``d_max_m``; the
error measure renders at the camera's width (at most 10 px per stripe), whose pixel grid a stripe composite
aliases on, unless ``width`` asks for a cheaper one, docs/planning.md §8):
modality ``stripes`` or ``flood``, with or without the polarizer. With a frame budget (``max_frames``) a
stripe plan takes the fewest sheets per frame that fit it (two analyzer passes with ``analyzer = "stage"``),
renders those K-sheet frames (their backscatter) and keeps to separations where the sheets stay apart in the
image over the scene's objects' depth range (:mod:`polarstripe.planning.sheets`;
``curves["sheets_allowed"]``). :class:`Plan` carries the sheets, the best separation of the mean curve, the
scan type (``rotate``, ``translate`` or ``both``) and per-location optima for stripes, and the curves
(``separation_m``, ``objective``, ``objective_noise_free``, ``quality``, ``weight``, and ``objective_O1``…
per observed location).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np
from polarstripe.msgs import Empty, MediumEstimate, Plan
from polarstripe.planning.image_model import ImageModel, plan_fidelity
from polarstripe.planning.medium_dop import with_measured_p
from polarstripe.planning.planner import DEFAULT_SEARCH, default_separations, plan, plan_model, resolve_search
from polarstripe.planning.sheets import feasible, sheet_limits, sheets_for_budget
from polarstripe.runtime.liveness import RunState
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams, check_frame_size
from polarstripe.runtime.process import interruptible
from polarstripe.sim.render import render_frame, resolve_fidelity
from polarstripe.sim.scene import Phase, SceneError, load_scene, parse_size, with_light
from polarstripe.sim.scene_calibration import with_calibration


class Planner(Node):
    """Serves and publishes the placement plan; re-plans when the medium estimate moves (module docstring)."""

    class Params(NodeParams):
        scene: str = ""  # scene TOML; "" = the paper's tank
        calibration: str = ""  # rig calibration file: the camera's and projector's pinholes (docs/depth.md)
        resolution: str = ""  # camera "WxH"; "" = the scene's
        fidelity: str = "preview"  # the simulator's levels; the error measure also "draft" (planning.md §8)
        orders: Literal["all", "single"] = "all"  # the model's: as the scene needs (sim/orders.py) | paper's
        measure: Literal["error", "paper"] = "error"  # expected error vs T | CQM, margin (docs/planning.md)
        modality: Literal["stripes", "flood"] = "stripes"
        polarized: bool = True
        light: Literal["scene", "linear", "circular"] = "scene"  # the polarization optics (sim with_light)
        stripes: int = 30
        max_frames: int = 0  # frame budget of a stripe scan: the fewest sheets per frame that fit (0: one)
        analyzer: Literal["stage", "mosaic"] = "stage"  # polarized scans: two passes (stage) or one (mosaic)
        stripe_step: int = 3  # error measure: every n-th frame of a stripe scan (1: all; 3 costs a third)
        width: int = 0  # error measure: the renders' width [px]; 0 = the camera's, at most 10 px a stripe
        search: Literal["coarse", "exhaustive"] = DEFAULT_SEARCH  # which separations (planning.md §8)
        separations: int = 0  # the search's first, even grid; 0 = the search's
        d_min_m: float = 0.02
        d_max_m: float = 0.5
        refine: int = -1  # bisection rounds around the curves' peaks; -1 = the search's
        rivals: float = -1.0  # local maxima within this relative loss of the best's refined too; -1: search's
        exposure: Literal["scene", "auto"] = "scene"
        max_saturated_fraction: float = 1.0  # of a flood frame at the plan's separation; 1 = no check
        publish_on_start: bool = True
        publish_delay_s: float = 1.0
        replan: bool = True
        p_tolerance: float = 0.05  # absolute
        sigma_tolerance: float = 0.1  # relative
        g_tolerance: float = 0.02  # absolute, the phase function's mean cosine

        def validate(self):
            super().validate()
            if self.separations == 1 or self.separations < 0 or not 0 < self.d_min_m < self.d_max_m:
                raise ValueError(f"need separations 0 (the search's) or >= 2 and 0 < d_min_m < d_max_m, got "
                                 f"{self.separations}, {self.d_min_m}, {self.d_max_m}")
            if self.width and self.width < 8:
                raise ValueError(f"width must be 0 (the camera's) or at least 8 pixels, got {self.width}")
            if self.refine < -1:
                raise ValueError(f"refine must be >= 0 rounds (-1: the search's), got {self.refine}")
            if self.rivals < 0 and self.rivals != -1:
                raise ValueError(f"rivals must be >= 0 (-1: the search's), got {self.rivals}")
            if self.stripe_step < 1:
                raise ValueError(f"stripe_step must be at least 1, got {self.stripe_step}")
            if not 0.0 <= self.max_saturated_fraction <= 1.0:
                raise ValueError(f"max_saturated_fraction must be in [0, 1], got "
                                 f"{self.max_saturated_fraction}")
            if self.p_tolerance < 0 or self.sigma_tolerance < 0:
                raise ValueError("p_tolerance and sigma_tolerance must be >= 0")
            if self.stripes < 1:
                raise ValueError(f"stripes must be >= 1, got {self.stripes}")
            if self.max_frames < 0:
                raise ValueError(f"max_frames must be >= 0 (0: no budget), got {self.max_frames}")
            if self.max_frames and (self.modality != "stripes" or self.measure != "error"):
                raise ValueError("max_frames plans sheets per stripe frame: modality 'stripes', measure "
                                 "'error'")
            # e.g. "ultra": one line naming the choices; the error measure also has the planner's "draft"
            (plan_fidelity if self.measure == "error" else resolve_fidelity)(self.fidelity)
            if self.resolution:
                check_frame_size(*parse_size(self.resolution), what="resolution")

    PUBLISHES = {"planner/plan": Plan}
    SUBSCRIBES = {"medium/estimate": MediumEstimate, "compositor/medium_p": MediumEstimate}
    SERVES = {"planner/plan": (Empty, Plan)}

    def setup(self):

        scene = load_scene(self.params.scene or None)
        if self.params.calibration:  # the real rig's pinholes (sim/scene_calibration.py)
            size = parse_size(self.params.resolution) if self.params.resolution else None
            try:
                scene = with_calibration(scene, self.params.calibration, cam_size=size)
            except SceneError as exc:
                raise SceneError(f"node {self.name!r}: param 'calibration': {exc}") from None
        if self.params.resolution:  # as the simulator does: exposure scaled to keep the DN level
            scene = scene.replace(camera=scene.camera.resized(parse_size(self.params.resolution)))
        self.scene = scene if self.params.light == "scene" else with_light(scene, self.params.light)
        self.run_state = RunState.of(self.graph, self.name)  # a re-plan's medium outlives a respawn
        if "medium_p" in self.run_state:
            state, d_max = self.run_state, self.params.d_max_m  # at_m: where p was measured
            self.scene = self.with_medium(state.get("medium_p"), state.get("medium_sigma_t"),
                                          state.get("medium_g"), state.get("medium_at_m", d_max))
            self.log.info("medium restored from the run state: p %.3f, sigma_t %.3g /m",
                          self.run_state.get("medium_p"), self.scene.medium.sigma_t)
        self.counters["replans"] = 0
        self.plan_pub = self.publisher("planner/plan")
        self.fitted_p = False  # an in-situ fit's p outranks the compositor's
        self.subscribe("medium/estimate", self.on_estimate, mode="latest")
        self.subscribe("compositor/medium_p", self.on_compositor_p, mode="latest")
        self.serve("planner/plan", self.on_request)
        self.plan = self.make_plan()
        if self.params.publish_on_start:
            self.every(self.params.publish_delay_s, self._publish_once, name="publish_on_start")

    def make_plan(self) -> Plan:
        """Sweep the separations on the current scene; remember the p and σ_t the plan assumed."""

        p = self.params
        s = resolve_search(p.search, separations=p.separations or None,        # 0 and -1: the search's own
                           refine=None if p.refine < 0 else p.refine,
                           rivals=None if p.rivals < 0 else p.rivals)
        seps = default_separations(s.separations, p.d_min_m, p.d_max_m)
        passes = 2 if p.polarized and p.analyzer == "stage" else 1
        sheets = sheets_for_budget(p.stripes, p.max_frames, passes) if p.max_frames else 1
        allowed = feasible(sheet_limits(self.scene, p.stripes, seps), sheets) if sheets > 1 else \
            np.ones(seps.size, bool)
        if not allowed.any():
            raise SceneError(f"a budget of {p.max_frames} frames needs {sheets} sheets per frame, and over "
                             "the depth range of the scene's objects they overlap in the image at every "
                             "separation: allow more frames or scan fewer stripes")
        model = plan_model(self.scene, measure=p.measure, fidelity=p.fidelity, n_stripes=p.stripes,
                           orders=p.orders, stripe_step=p.stripe_step, sheets=sheets, width=p.width or None)
        plans = plan(model, seps, modalities=(p.modality,), exposure=p.exposure, refine=s.refine,
                     rivals=s.rivals)
        mp = plans[p.modality + ("_polarized" if p.polarized else "")]
        c = mp.curve
        if sheets > 1:          # the bisections' separations too (the grid's were checked above)
            extra = ~np.isin(np.round(c.separations_m, 9), np.round(seps, 9))
            ok = np.ones(c.separations_m.size, bool)
            ok[~extra] = allowed
            if extra.any():
                ok[extra] = feasible(sheet_limits(self.scene, p.stripes, c.separations_m[extra]), sheets)
            allowed = ok
        else:
            allowed = np.ones(c.separations_m.size, bool)
        # the objective counts the planned method's saturated pixels as lost (planning/predicted_error.py);
        # a user may also keep a flood frame at the plan's separation (the brightest of any method, every
        # method of a scan uses it) below full scale: max_saturated_fraction < 1
        guard = p.max_saturated_fraction < 1.0
        order = [i for i in np.argsort(-c.objective, kind="stable") if allowed[i]]  # sheets apart
        saturated = None
        frames = model if isinstance(model, ImageModel) else ImageModel(   # the error measure's width
            self.scene, fidelity=p.fidelity, n_stripes=p.stripes, orders=p.orders, width=p.width or None)
        if guard:
            saturated = np.array([frames.saturated_fraction(d) for d in c.separations_m])
        usable = [i for i in order if not guard or saturated[i] <= p.max_saturated_fraction]
        best = float(c.separations_m[usable[0] if usable else order[0]])
        if not usable:
            self.log.warning("every separation saturates more than %.0f %% of a flood frame: the plan keeps "
                             "the best objective", 100 * p.max_saturated_fraction)
        elif usable[0] != order[0]:
            self.log.info("the best objective (d_LC = %.3f m) saturates %.0f %% of a flood frame: "
                          "using %.3f m", c.separations_m[order[0]], 100 * saturated[order[0]], best)
        # the p an estimate reports (the flood's backscatter-weighted DOP, planning/medium_p.py) for this plan
        self.p_assumed = frames.backscatter_dop(best)
        self.sigma_assumed = float(self.scene.medium.sigma_t)
        self.g_assumed = float(self.scene.medium.phase.g)
        curves = {"separation_m": c.separations_m, "objective": c.objective,
                  "objective_noise_free": c.objective_noise_free, "quality": c.quality, "weight": c.weight,
                  "sheets_allowed": allowed.astype(float)}
        if guard:
            curves["flood_saturated_fraction"] = saturated
        for i, lc in enumerate(mp.location_curves):
            curves[f"objective_O{i + 1}"] = lc.objective
        result = Plan(modality=p.modality, separation_m=best, scan_type=mp.scan["winner"] if mp.scan else "",
                      stripe_optima=[lc.best_separation_m for lc in mp.location_curves],
                      curves={k: np.asarray(v, np.float64) for k, v in curves.items()}, sheets=sheets)
        self.log.info("plan: %s%s, d_LC = %.3f m%s, %d sheet(s) per frame (assumes p = %.3f, sigma_t = "
                      "%.3g /m)", p.modality, " polarized" if p.polarized else "", best,
                      f", scan {result.scan_type}" if result.scan_type else "", sheets, self.p_assumed,
                      self.sigma_assumed)
        return result

    def _publish_once(self):
        self.cancel("publish_on_start")
        self.plan_pub.publish(self.plan)

    def on_request(self, request: Empty) -> Plan:
        self.plan_pub.publish(self.plan)
        return self.plan

    def with_medium(self, p: float, sigma_t: float | None, mean_cosine: float | None, at_m: float):
        """The scene with, when given, ``sigma_t`` [1/m], the TTHG ``mean_cosine`` and the DOP model that
        gives the measured ``p`` with the source at ``at_m`` [m], where it was measured
        (planning/medium_dop.py: the Rayleigh model's δ, so the DOP still varies across the image; a
        constant model: p)."""
        medium = self.scene.medium
        if sigma_t is not None:
            medium = medium.replace(sigma_t=float(sigma_t))
        if mean_cosine is not None:
            medium = medium.replace(phase=Phase("tthg", min(max(float(mean_cosine), 0.0), 0.999)))
        scene = self.scene.replace(medium=medium)
        if p is not None and math.isfinite(p):
            scene = with_measured_p(scene, p, at_m, fidelity=self.params.fidelity)
            if scene.medium.dop.model == "rayleigh":
                self.log.info("DOP model: depolarization %.3f gives p %.3f at d_LC = %.3f m",
                              scene.medium.dop.depolarization, p, at_m)
        return scene

    def on_estimate(self, est: MediumEstimate) -> None:
        """The estimator's fit: re-plan if it moved, and publish the plan either way, as the answer to that
        estimate (``curves["estimate_scan_id"]``: its scan id; the sequencer's rescan waits for it)."""
        self.fitted_p |= math.isfinite(est.p)
        self.replan_on(est)
        curves = {**self.plan.curves, "estimate_scan_id": np.array([float(est.scan_id)])}
        self.plan = dataclasses.replace(self.plan, curves=curves)
        self.plan_pub.publish(self.plan)

    def on_compositor_p(self, est: MediumEstimate) -> None:
        if not self.fitted_p and self.replan_on(est):
            self.plan_pub.publish(self.plan)

    def replan_on(self, est: MediumEstimate) -> bool:
        """Re-plan when ``est`` differs from the plan's medium beyond the tolerances."""
        p = self.params
        dp = abs(est.p - self.p_assumed) if math.isfinite(est.p) else 0.0
        sigma, g = (None, None) if est.reason else (est.sigma_t_per_m, est.mean_cosine)
        ds = abs(sigma - self.sigma_assumed) / max(self.sigma_assumed, 1e-12) if sigma is not None else 0.0
        dg = abs(g - self.g_assumed) if g is not None else 0.0
        if not p.replan or (dp <= p.p_tolerance and ds <= p.sigma_tolerance and dg <= p.g_tolerance):
            return False
        self.log.info("medium estimate of scan %d (p %.3f, sigma_t %s) differs from the plan's (p %.3f, "
                      "sigma_t %.3g): re-planning", est.scan_id, est.p, sigma, self.p_assumed,
                      self.sigma_assumed)
        at_m = self.plan.separation_m                    # where the estimate's scan was made
        self.scene = self.with_medium(est.p, sigma, g, at_m)
        medium_p = est.p if math.isfinite(est.p) else self.p_assumed
        self.run_state.save(medium_p=medium_p, medium_sigma_t=sigma, medium_g=g,  # for a respawned planner
                            medium_at_m=at_m)
        with interruptible("re-planning"):  # seconds of pure computation: a Ctrl-C need not wait for it
            self.plan = self.make_plan()
        self.counters["replans"] += 1
        return True


def warm_kernels() -> None:
    """Compile (or load from numba's cache) every kernel the rig's nodes use, in this process: a flood, a
    stripe and a checker frame and a small plan of the default tank. The launcher runs it before the graph
    starts (``[launch] prepare`` in launch/sim.toml), so on a cold machine no node spends its start-up
    compiling and no start-up wait races the compiler; with a warm cache it takes about a second."""

    scene = load_scene(None)
    scene = scene.replace(camera=scene.camera.resized((32, 24)))
    for fidelity in ("preview", "standard"):
        for pattern in ("flood", "stripe:3/8", "checker:8:0"):
            render_frame(scene, pattern, polarizer_deg=0.0, fidelity=fidelity, seed=0)
    for measure in ("error", "paper"):
        model = plan_model(scene, measure=measure, fidelity="preview", n_stripes=8)
        plan(model, default_separations(3, 0.05, 0.4), modalities=("stripes", "flood"))


NODE = Planner
