"""The estimator node: σ_t, the phase function's mean cosine g and the backscatter DOP p of the medium,
fitted in situ to the frames the scans already take (the fit is docs/planning.md §6,
:func:`polarstripe.planning.medium_fit.fit_medium`).

It listens to ``emitter/scan`` and ``camera/frame`` and keeps, per source pose, the last flood frame (a
``flood`` scan, or the mean of a ``polarized_flood`` scan's analyzer pair) and that pair (E_b at the scan's
first analyzer angle, E_w at the second) for p. When a ``stripes`` or ``polarized_stripes`` scan is done at a
pose not yet fitted, its stripe frames, the flood and the pair go to the fit with the rig's scene at that
pose: the separation from ``simulator/truth`` of that scan (``metrics["separation_m"]``), else the last
``planner/plan``, else the scene's; the exposure from the frames; the object-free pixels for p where the
truth's ``depth_m`` is 0 (else the whole frame).

The fit takes seconds, so it runs in a worker thread; a timer of the loop (``poll_s``) collects it, so the
node keeps handling frames and scans (and the runner's thread keeps beating) meanwhile. One fit runs at a
time; a stripe scan done meanwhile at another pose waits for it (only the newest waits).

Frames are block-averaged to about ``fit_width`` pixels across before the fit
(:func:`~polarstripe.planning.medium_fit.downsample`; a block with a saturated pixel stays saturated). The
fit's model must run at the resolution the frames were rendered at (docs/planning.md §6: at σ_t 3, g 0.9
frames of a 320×240 camera fitted at 160×120 gave σ_t 6 % high, at 80×60 23 %): the simulator's preview model
renders at about 160 px across and resizes to the camera, so ``fit_width = 0`` (auto) fits at ``model_width``
(160) or the camera's width if smaller; at another ``fidelity`` (the simulator's, which launch/sim.toml
passes) at the camera's width, which is slow (not measured). A fit at 160×120 took 18–26 s on the loaded
2-core machine.

Publishes ``medium/estimate`` (:class:`MediumEstimate`, the only publisher of that topic): σ_t, g and p with
their 1σ uncertainties, or a non-empty ``reason`` with σ_t and g None (no visible sheet, saturation, noise, a
fit at a bound, the model not describing the frames); p is NaN when the scans had no analyzer pair.
"""

from __future__ import annotations

import math
import threading
import time
from concurrent.futures import Future

import numpy as np
from polarstripe.msgs import Composite, Frame, MediumEstimate, Method, Plan, ScanEvent
from polarstripe.planning.medium_fit import FitSettings, ScanFrames, downsample, fit_medium
from polarstripe.planning.medium_p import p_of_pair
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams, check_frame_size
from polarstripe.sim.render import resolve_fidelity
from polarstripe.sim.scene import load_scene, parse_size, with_separation
from polarstripe.sim.sensor import dark_offset_dn, full_scale_dn


class Estimator(Node):
    """Fits the medium to each new pose's stripe scan and publishes ``medium/estimate`` (module docstring)."""

    class Params(NodeParams):
        scene: str = ""  # scene TOML; "" = the paper's tank (its σ_t and g are not used)
        resolution: str = ""  # the camera's "WxH" (as the simulator's); "" = the scene's
        fidelity: str = "preview"  # the model the fit renders: the simulator's
        model_width: int = 160  # the width the simulator's preview model runs at (other fidelities: the
        # camera's, its render_scale is 1 there)
        fit_width: int = 0  # frames block-averaged to about this width; 0 = auto (module docstring)
        stripes_used: int = 4  # stripe frames of a scan the fit reads (evenly spread)
        poll_s: float = 0.1  # how often the loop looks for a finished fit

        def validate(self):
            super().validate()
            resolve_fidelity(self.fidelity)
            if self.resolution:
                check_frame_size(*parse_size(self.resolution), what="resolution")
            if self.fit_width < 0 or self.model_width < 2 or self.stripes_used < 1 or not self.poll_s > 0:
                raise ValueError("need fit_width >= 0, model_width >= 2, stripes_used >= 1 and poll_s > 0")

    PUBLISHES = {"medium/estimate": MediumEstimate}
    SUBSCRIBES = {"camera/frame": Frame, "emitter/scan": ScanEvent, "simulator/truth": Composite,
                  "planner/plan": Plan}

    def setup(self):
        scene = load_scene(self.params.scene or None)
        if self.params.resolution:  # as the simulator does: exposure scaled to keep the DN level
            scene = scene.replace(camera=scene.camera.resized(parse_size(self.params.resolution)))
        self.scene = scene
        self.scans: dict[int, dict] = {}  # scan id -> {"event": start ScanEvent, "frames": [Frame]}
        self.truths: dict[int, Composite] = {}
        self.plan_sep: float | None = None
        self.floods: dict[float, dict] = {}  # separation -> {"flood": [frames], "pair": (E_b, E_w), "free"}
        self.fitted: set[float] = set()
        self.pending: dict | None = None  # the newest fit waiting for the worker
        self.job: tuple[Future, dict] | None = None
        for key in ("estimates", "refusals", "frames_ignored"):
            self.counters[key] = 0
        self.pub = self.publisher("medium/estimate")
        self.subscribe("emitter/scan", self.on_scan, mode="all")
        self.subscribe("camera/frame", self.on_frame, mode="all")
        self.subscribe("simulator/truth", self.on_truth, mode="all")
        self.subscribe("planner/plan", self.on_plan, mode="latest")
        self.every(self.params.poll_s, self.collect, name="collect")

    # ---- messages ------------------------------------------------------------------------------------------
    def on_plan(self, plan: Plan) -> None:
        self.plan_sep = float(plan.separation_m)

    def on_truth(self, truth: Composite) -> None:
        self.truths[truth.scan_id] = truth
        for sid in [s for s in self.truths if s < truth.scan_id - 8]:
            del self.truths[sid]

    def on_frame(self, frame: Frame) -> None:
        scan = self.scans.get(frame.scan_id)
        if scan is None:
            self.counters["frames_ignored"] += 1  # a scan it does not use (hf_separation, calibration)
            return
        scan["frames"].append(frame)

    def on_scan(self, event: ScanEvent) -> None:
        if event.event == "start":
            method = Method.lookup(event.method)
            if method is not None and method.family in ("stripe", "flood"):  # not hf_separation's checkers
                self.scans = {event.scan_id: {"event": event, "frames": []}}  # one scan at a time
            return
        scan = self.scans.pop(event.scan_id, None)
        if scan is None or event.event != "done":
            return
        method, frames = Method(scan["event"].method), scan["frames"]
        sep = self.separation(event.scan_id)
        if method.family == "flood":
            self.keep_flood(sep, scan["event"], frames, self.truths.get(event.scan_id))
        elif sep not in self.fitted and frames:
            self.fitted.add(sep)
            self.pending = {"scan_id": event.scan_id, "sep": sep, "frames": frames,
                            **self.floods.get(sep, {})}
            self.collect()

    def separation(self, scan_id: int) -> float:
        """The source's separation [m] during ``scan_id`` (rounded to 0.1 mm, the key of a pose)."""
        truth = self.truths.get(scan_id)
        if truth is not None and "separation_m" in truth.metrics:
            return round(float(truth.metrics["separation_m"]), 4)
        if self.plan_sep is not None:
            return round(self.plan_sep, 4)
        return round(float(self.scene.separation_m()), 4)

    def keep_flood(self, sep: float, start: ScanEvent, frames: list[Frame], truth: Composite | None) -> None:
        floods = [f for f in frames if f.pattern == "flood"]
        if not floods:
            return
        keep = self.floods.setdefault(sep, {})
        if not Method(start.method).polarized:
            keep["flood"] = [f.image for f in floods]
        elif len(start.analyzer_deg) == 2:  # E_b at the first angle, E_w at the second
            def nearest(f: Frame) -> int:
                return int(np.argmin([abs(((f.polarizer_deg or 0.0) - a + 90) % 180 - 90)
                                      for a in start.analyzer_deg]))
            eb = [f.image for f in floods if nearest(f) == 0]
            ew = [f.image for f in floods if nearest(f) == 1]
            if eb and ew:
                keep["pair"] = (eb[0], ew[0])
                keep.setdefault("flood", [eb[0], ew[0]])  # ½(k1 + k2)(D + A + B): docs/physics.md §4.1
        if truth is not None and "depth_m" in truth.images:
            keep["free"] = np.asarray(truth.images["depth_m"]) == 0
        keep["exposure_s"] = floods[0].exposure_s

    # ---- the fit -------------------------------------------------------------------------------------------
    def collect(self) -> None:
        """Publish a finished fit; start the pending one when the worker is free."""
        if self.job is not None and self.job[0].done():
            future, job = self.job
            self.job = None
            try:
                self.publish(job, *future.result())
            except Exception as exc:  # noqa: BLE001 — a fit that fails is a refusal, never a crash
                self.publish(job, None, math.nan, math.nan, 0.0, f"the fit failed: {exc}")
        if self.job is None and self.pending is not None:
            job, self.pending = self.pending, None
            self.job = (self.start_fit(job), job)

    def start_fit(self, job: dict) -> Future:
        """Run :meth:`fit` in a daemon thread: a stop never waits for a fit (a pool's worker would hold the
        process until the fit ends, beyond the launch's shutdown_timeout)."""
        future: Future = Future()

        def work():
            try:
                future.set_result(self.fit(job))
            except BaseException as exc:  # noqa: BLE001 — handed to the loop, which publishes a refusal
                future.set_exception(exc)

        threading.Thread(target=work, name="medium fit", daemon=True).start()
        return future

    def fit_width(self, width: int) -> int:
        if self.params.fit_width:
            return self.params.fit_width
        return min(width, self.params.model_width) if self.params.fidelity == "preview" else width

    def fit(self, job: dict):
        """In the worker: (MediumFit, p, p_std, seconds, reason)."""
        t0 = time.perf_counter()
        frames: list[Frame] = job["frames"]
        scene = with_separation(self.scene, job["sep"])
        scene = scene.replace(camera=scene.camera.replace(exposure_s=frames[0].exposure_s))
        w, h = scene.camera.resolution
        stripes: dict[str, list[np.ndarray]] = {}
        for f in frames:
            if f.image.shape != (h, w):
                return None, math.nan, math.nan, 0.0, (f"frame of {f.image.shape[1]}x{f.image.shape[0]} px, "
                                                      f"the estimator's camera is {w}x{h} (param resolution)")
            if f.pattern.startswith("stripe:"):
                stripes.setdefault(f.pattern, []).append(f.image)
        full = float(full_scale_dn(scene.camera))
        small, out, n_avg = downsample(scene, dict(stripes, flood=job.get("flood", [])),
                                       width=self.fit_width(w), full_scale=full)
        flood = out.pop("flood") or None
        scan = ScanFrames(out, flood, polarized_pair=job.get("pair"), object_free=job.get("free"),
                          frames_averaged=n_avg)
        result = fit_medium(small, scan, FitSettings(fidelity=self.params.fidelity,
                                                     n_stripes_used=self.params.stripes_used))
        p, p_std = result.p, result.p_std
        why_p = result.extra.get("p_reason", "no analyzer pair" if job.get("pair") is None else "")
        if math.isnan(p) and job.get("pair") is not None:
            dark = dark_offset_dn(scene.camera)
            p, p_std, why_p = p_of_pair(job["pair"], job.get("free"), dark, full - 0.5)
        return result, p, p_std, time.perf_counter() - t0, why_p

    def publish(self, job: dict, result, p: float, p_std: float, seconds: float, why_p: str) -> None:
        sid, sep = job["scan_id"], job["sep"]
        p_std_or = p_std if math.isfinite(p_std) else None
        if result is not None and result.ok:
            est = MediumEstimate(p=p, scan_id=sid, sigma_t_per_m=result.sigma_t_per_m,
                                 sigma_t_std=result.sigma_t_std, mean_cosine=result.mean_cosine,
                                 mean_cosine_std=result.mean_cosine_std, p_std=p_std_or)
            self.counters["estimates"] += 1
            self.log.info("scan %d (d_LC %.3f m): sigma_t %.3g ± %.2g /m, g %.3f ± %.3f, p %.3f ± %.3f%s "
                          "(fit %.1f s, %d px, chi2/dof %.2g)", sid, sep, est.sigma_t_per_m, est.sigma_t_std,
                          est.mean_cosine, est.mean_cosine_std, p, p_std,
                          f" ({why_p})" if why_p else "", seconds, result.pixels, result.chi2_per_dof)
        else:
            reason = why_p if result is None else result.reason
            est = MediumEstimate(p=p, scan_id=sid, p_std=p_std_or, reason=reason or "cannot estimate")
            self.counters["refusals"] += 1
            self.log.warning("scan %d (d_LC %.3f m): cannot estimate sigma_t and g: %s (p %.3f)", sid, sep,
                             est.reason, p)
        self.pub.publish(est)


NODE = Estimator
