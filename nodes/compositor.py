"""The compositor node: folds each scan's frames into running reductions and, when the scan is complete,
makes the method's composite, scores it and writes it out.

* subscribes ``camera/frame``, ``emitter/scan`` and ``simulator/truth`` (every message); each handler does
  its own work and returns (an event-driven state machine, never waiting on the bus). A frame of the running
  scan is folded in; one whose scan's ``start`` has not come yet is held (at most ``early_frames``; dropped,
  counted, if the start never comes). A scan is complete when its ``done`` has come and all its expected
  frames (patterns × analyzer angles) are in, or ``done_grace_s`` after the last frame (fault "n of m frames"
  in the log and metrics); the next scan's ``start``, should it overtake them (another socket), waits for them
  until then, or until a frame of its own comes (after all of the old scan's). A complete scan is held up to
  ``truth_wait_s`` for its ``simulator/truth`` message (tagged with the scan id; it can trail the frames in a
  replay), then composited without (error vs truth None); a topic silent for a whole wait is not waited for
  again (a rig without a simulator);

* per scan, a :class:`~polarstripe.imaging.composite.RunningComposite` keeps one per-pixel max and min per
  analyzer angle (buffers reused from scan to scan): memory does not grow with the number of stripes;
* the composite and its scores: :func:`polarstripe.imaging.compose.compose` and ``score`` (the pipeline of
  ``polarstripe compare`` too), in DN above the dark offset, saturated pixels masked; Michelson contrast over
  the chart's bars, ``error_vs_truth`` (relative RMS, gain fitted) against the truth's S;
* eq. 6's p (``p_rule``, docs/physics.md §4.2): ``map`` (default) per pixel from the medium's model
  (:mod:`polarstripe.nodes.compositor_p`: the ``p_scene``, its medium from ``medium/estimate``, the pose
  from the truth or ``planner/plan``), or from the frames alone; ``median``/``upper`` one p̂;
* publishes ``compositor/composite`` (images ``composite`` float32 DN, 0 where masked, ``saturated`` uint8,
  ``e_b``/``e_w`` or ``global``) and, after a polarized method, ``compositor/medium_p`` (p and its std);
  writes ``<out>/<method>.png``, ``.tiff``/``.npy``, ``metrics.json``, ``comparison.png``;
* a polarization camera's frame (``Frame.mosaic_deg``, a 2×2 micro-polarizer mosaic; the ``mosaic_*``
  params are the camera's calibration and the rule of the crossed angle, docs/physics.md §4.4) is folded as
  E_b and E_w of that one frame (polarized methods) or as its intensity a0·S0
  (:mod:`polarstripe.nodes.compositor_mosaic`); metrics ``mosaic`` say so;
* after a stripe scan, its depth (light-stripe triangulation with the ``geometry`` param's rig,
  :mod:`polarstripe.nodes.compositor_depth`): ``compositor/depth`` (``DepthMap``), ``depth_<method>.npy``
  and ``.ply``, ``metrics[method]["depth"]``; a scan of K sheets per frame (``ScanEvent.sheets``) tells each
  pixel's sheet by the ``depth_range_m`` param (:mod:`polarstripe.imaging.sheets`), and one whose sheets
  overlap in the image has no depth, ``metrics[method]["depth"]["error"]`` saying why.

Calibration frames of the polarizer (scan ids from 2**30) are ignored. Frames that do not belong are dropped
and counted (heartbeat counters ``frames_unexpected`` no scan running / never started,
``frames_mismatched`` another scan id, ``frames_bad`` shape/dtype/ndim, ``frames_duplicate`` a step seen
twice, ``frames_bad_pattern`` a pattern the method does not use, ``frames_bad_angle`` an analyzer angle not in
the scan).
"""

from __future__ import annotations

import json
import os
from collections import deque

import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.imaging.compose import compose
from polarstripe.imaging.composite import RunningComposite
from polarstripe.imaging.validation import ImagingError
from polarstripe.msgs import (
    CALIBRATION_SCAN_ID,
    METHOD_NAMES,
    Composite,
    DepthMap,
    Frame,
    MediumEstimate,
    Method,
    Plan,
    ScanEvent,
)
from polarstripe.nodes.compositor_depth import DepthStage
from polarstripe.nodes.compositor_mosaic import MosaicViews
from polarstripe.nodes.compositor_output import PublishedDepth, fmt, write_comparison, write_method
from polarstripe.nodes.compositor_p import MediumModel
from polarstripe.nodes.compositor_params import CompositorParams
from polarstripe.nodes.compositor_scan import Scan, roi, scan_metrics
from polarstripe.runtime.node import Node

_DROPS = ("frames_unexpected", "frames_mismatched", "frames_bad", "frames_duplicate", "frames_bad_pattern",
          "frames_bad_angle")
FRAMES_DEADLINE, TRUTH_DEADLINE = "frames_deadline", "truth_deadline"  # the node's two one-shot timers
TRUTHS_KEPT = 8  # truth messages of scans not finished yet


class Compositor(Node):
    """Running reductions per scan, the method's composite, its metrics and files (module docstring)."""

    Params = CompositorParams

    PUBLISHES = {"compositor/composite": Composite, "compositor/medium_p": MediumEstimate,
                 "compositor/depth": DepthMap}
    SUBSCRIBES = {"camera/frame": Frame, "emitter/scan": ScanEvent, "simulator/truth": Composite,
                  "medium/estimate": MediumEstimate, "planner/plan": Plan}

    def setup(self):
        self.scan: Scan | None = None
        self.running = None  # RunningComposite, reused across scans of one shape and dtype
        self.results: dict[str, np.ma.MaskedArray] = {}  # the last composite of each method
        self.metrics: dict[str, dict] = {}
        self.early: deque[Frame] = deque()  # frames ahead of their scan's start
        self.truths: dict[int, Composite] = {}  # scan id -> its simulator/truth message
        self._last_start = -1  # the newest scan id started
        self._pending_start: ScanEvent | None = None  # a start held until the running scan's frames are in
        self._truth_heard = self._truth_silent = False
        for key in (*_DROPS, "frames_calibration", "scans_done", "scans_failed"):
            self.counters[key] = 0
        self.composite_pub = self.publisher("compositor/composite")
        self.estimate_pub = self.publisher("compositor/medium_p")
        self.mosaic, self.medium = MosaicViews(self.params), MediumModel(self.params)
        self.medium.warm()
        self.depth = DepthStage.of(self.params, PublishedDepth(self.publisher("compositor/depth")), self.log)
        self.subscribe("camera/frame", self.on_frame, mode="all")
        self.subscribe("emitter/scan", self.on_scan, mode="all")
        if self.params.use_truth:
            self.subscribe("simulator/truth", self.on_truth, mode="all")
        self.subscribe("medium/estimate", self.medium.on_estimate, mode="latest")
        self.subscribe("planner/plan", self.medium.on_plan, mode="latest")
        if self.params.out:
            os.makedirs(self.params.out, exist_ok=True)
            path = os.path.join(self.params.out, "metrics.json")
            if os.path.exists(path):
                with open(path) as f:
                    self.metrics = json.load(f)

    # ---- frames ----------------------------------------------------------------------------------------
    def on_frame(self, frame: Frame) -> None:
        if frame.scan_id >= CALIBRATION_SCAN_ID:
            self.counters["frames_calibration"] += 1  # the polarizer's, not a scan's
            return
        scan = self.scan
        if self._pending_start is not None and frame.scan_id >= self._pending_start.scan_id:
            self._start_pending()  # the running scan's frames came before this one: it ends with them
            scan = self.scan
        if scan is not None and frame.scan_id == scan.scan_id:
            self._fold(scan, frame)
            self._advance(scan)
        elif frame.scan_id > self._last_start:  # its "start" has not come yet: held
            self.early.append(frame)
            if len(self.early) > self.params.early_frames:
                self._drop("frames_unexpected", self.early.popleft(), "held, but its scan did not start")
        elif scan is None:
            self._drop("frames_unexpected", frame, "no scan running")
        else:
            self._drop("frames_mismatched", frame, f"the running scan is {scan.scan_id}")

    def _drop(self, why: str, frame: Frame, detail: str = "") -> None:
        self.counters[why] += 1
        if self.scan is not None and frame.scan_id == self.scan.scan_id:
            self.scan.dropped += 1
        n = self.counters[why]
        if n <= 3 or n % 100 == 0:
            self.log.warning("dropped frame (scan %d step %d): %s%s (%d so far)", frame.scan_id,
                             frame.step, why.removeprefix("frames_").replace("_", " "),
                             f": {detail}" if detail else "", n)

    def _fold(self, scan: Scan, frame: Frame) -> None:
        """Check a frame of ``scan`` and fold it into the running reductions, or drop it."""
        image = frame.image
        if image.ndim != 2 or image.dtype.kind not in "uif" or image.size == 0:
            return self._drop("frames_bad", frame, f"image {image.dtype} {image.shape}")
        if frame.step in scan.steps:
            return self._drop("frames_duplicate", frame)
        if not Method(scan.method).accepts(frame.pattern):
            return self._drop("frames_bad_pattern", frame, f"{frame.pattern!r} in a {scan.method} scan")
        sat = self.params.saturation_dn
        sat = float((1 << frame.bit_depth) - 1) if sat is None and image.dtype.kind in "ui" else sat
        if frame.mosaic_deg:  # a polarization camera's raw mosaic: E_b and E_w (or S0) from this one frame
            if scan.analyzer_deg:
                return self._drop("frames_bad_angle", frame,
                                  f"a mosaic frame in a scan at {scan.analyzer_deg}")
            try:
                views = self.mosaic.views(frame, Method(scan.method).polarized, sat)
            except ImagingError as exc:
                return self._drop("frames_bad", frame, str(exc))
            sat, scan.mosaic = self.mosaic.saturation, list(frame.mosaic_deg)
        else:
            key = scan.angle_key(frame.polarizer_deg, self.params.angle_tolerance_deg)
            if key is False:
                return self._drop("frames_bad_angle", frame,
                                  f"{frame.polarizer_deg} not in {scan.analyzer_deg}")
            views = {key: image}
        image = next(iter(views.values()))
        rc = self.running
        if scan.frames == 0 and (rc is None or rc.shape != image.shape or rc.dtype != image.dtype):
            rc = self.running = RunningComposite(image.shape, image.dtype, saturation=sat)
        elif rc.shape != image.shape or rc.dtype != image.dtype:
            return self._drop("frames_bad", frame,
                              f"{image.dtype} {image.shape}, scan has {rc.dtype} {rc.shape}")
        for key, view in views.items():
            rc.add(view, key)
            self.depth.add(view, frame.pattern, key)
        scan.steps.add(frame.step)
        scan.frames, scan.bit_depth = scan.frames + 1, frame.bit_depth

    # ---- scans -----------------------------------------------------------------------------------------
    def on_scan(self, ev: ScanEvent) -> None:
        if self._pending_start is not None and ev.scan_id >= self._pending_start.scan_id:
            self._start_pending()  # an event of the held scan or a later one: the old scan cannot wait
        if ev.event == "start":
            old = self.scan
            if old is not None and old.done and not old.complete and not old.waiting_truth:
                # frames and scan events arrive on separate sockets: the old scan's last frames may still be
                # in flight behind this start. The start is held until they are in, the frames deadline
                # passes, or a frame of this scan or a later one comes (after all of them).
                self._pending_start = ev
                return None
            return self._start(ev)
        scan = self.scan
        if scan is None or ev.scan_id != scan.scan_id:
            self.log.warning("scan %d %s: not the running scan", ev.scan_id, ev.event)
        elif ev.event == "fault":
            self.log.error("scan %d (%s) ended on a fault: %s", ev.scan_id, scan.method, ev.detail)
            self.counters["scans_failed"] += 1
            self._close()
            self._start_pending()
        else:
            scan.done = True
            self._advance(scan)

    def _start(self, ev: ScanEvent) -> None:
        old = self.scan
        if old is not None and old.done:  # still waiting for frames or its truth: finished with what it has
            self._short(old)
            self._end_scan(old)
        elif old is not None:
            self.log.warning("scan %d started before scan %d ended: the old one is dropped", ev.scan_id,
                             old.scan_id)
            self._close()
        self._last_start = max(self._last_start, ev.scan_id)
        if ev.method not in METHOD_NAMES:
            self.log.error("scan %d: unknown method %r (known: %s)", ev.scan_id, ev.method,
                           ", ".join(METHOD_NAMES))
            return
        scan = self.scan = Scan(ev.scan_id, ev.method, ev.stripes, [float(a) for a in ev.analyzer_deg],
                                sheets=max(1, ev.sheets))
        self.depth.start(ev.method, ev.stripes, scan.sheets)
        if self.running is not None:
            self.running.reset()
        held, self.early = self.early, deque()
        for frame in held:  # frames that came ahead of this start: its own are folded in
            if frame.scan_id == scan.scan_id:
                self._fold(scan, frame)
            elif frame.scan_id < scan.scan_id:
                self._drop("frames_unexpected", frame, "its scan never started")
            else:
                self.early.append(frame)

    def _advance(self, scan: Scan) -> None:
        """After a frame or the "done" event: finish the scan once it is done and complete, else (re)arm the
        deadline for the frames still in flight."""
        if not scan.done or scan.waiting_truth:
            return
        if scan.complete:
            self.cancel(FRAMES_DEADLINE)
            self._settle(scan)
        else:
            self._arm(FRAMES_DEADLINE, self.params.done_grace_s, self._frames_deadline)

    def _frames_deadline(self) -> None:
        self.cancel(FRAMES_DEADLINE)
        scan = self.scan
        if scan is not None and scan.done and not scan.waiting_truth:
            self._short(scan)
            self._settle(scan)

    def _short(self, scan: Scan) -> None:
        """Note a scan that ends with frames missing."""
        if scan.expected is not None and not scan.complete:
            scan.fault = f"{scan.frames} of {scan.expected} frames"
            self.log.warning("scan %d: %s", scan.scan_id, scan.fault)

    def _settle(self, scan: Scan) -> None:
        """The frames are in: finish now, or hold the scan for its truth message."""
        if self.params.use_truth and scan.scan_id not in self.truths and not self._truth_silent:
            scan.waiting_truth = True
            self._arm(TRUTH_DEADLINE, self.params.truth_wait_s, self._truth_deadline)
        else:
            self._end_scan(scan)

    def on_truth(self, truth: Composite) -> None:
        self._truth_heard, self._truth_silent = True, False
        self.truths[truth.scan_id] = truth
        while len(self.truths) > TRUTHS_KEPT:
            del self.truths[next(iter(self.truths))]
        scan = self.scan
        if scan is not None and scan.waiting_truth and truth.scan_id == scan.scan_id:
            self._end_scan(scan)

    def _truth_deadline(self) -> None:
        self.cancel(TRUTH_DEADLINE)
        scan = self.scan
        if scan is None or not scan.waiting_truth:
            return
        if not self._truth_heard:
            self._truth_silent = True
            self.log.info("no ground truth on simulator/truth within %g s: not waited for again",
                          self.params.truth_wait_s)
        self._end_scan(scan)

    def _arm(self, timer: str, delay_s: float, callback) -> None:
        self.cancel(timer)
        self.every(delay_s, callback, name=timer)

    def _close(self) -> None:
        self.cancel(FRAMES_DEADLINE)
        self.cancel(TRUTH_DEADLINE)
        self.scan = None

    def _start_pending(self) -> None:
        """The start held while the previous scan waited for its last frames: that scan ends with what it
        has (if it has not ended), then this one starts."""
        ev, self._pending_start = self._pending_start, None
        if ev is not None:
            self._start(ev)

    def _end_scan(self, scan: Scan) -> None:
        """Close the scan and publish its composite, or (nothing to composite) a Composite with
        ``metrics["error"]``."""
        self._close()
        try:
            self._composite(scan)
        except PolarstripeError as exc:  # published, so that nobody waits for a composite in vain
            self.counters["scans_failed"] += 1
            self.log.error("scan %d (%s): no composite: %s", scan.scan_id, scan.method, exc)
            m = {"error": str(exc), "frames": scan.frames, **({"fault": scan.fault} if scan.fault else {})}
            self.composite_pub.publish(Composite(images={}, method=scan.method, scan_id=scan.scan_id,
                                                 metrics=m))
        self._start_pending()

    # ---- the composite ---------------------------------------------------------------------------------
    def _truth_of(self, scan: Scan, shape) -> Composite | None:
        """The scan's ``simulator/truth`` message if it came and fits frames of ``shape``, else None."""
        if not self.params.use_truth:
            return None
        truth = self.truths.pop(scan.scan_id, None)
        for old in [k for k in self.truths if k < scan.scan_id]:
            del self.truths[old]
        if truth is None:
            self.log.info("scan %d (%s): no ground truth for it on simulator/truth: no error vs truth",
                          scan.scan_id, scan.method)
        elif truth.images["S"].shape != shape:
            self.log.warning("truth is %s, frames are %s: not used", truth.images["S"].shape, shape)
            truth = None
        return truth

    def _composite(self, scan: Scan) -> None:
        """Compose and score the scan, publish it (and p) and write its files; PolarstripeError when there
        is nothing to composite."""
        if scan.frames == 0:
            raise PolarstripeError("no frames")
        rc, p = self.running, self.params
        truth = self._truth_of(scan, rc.shape)
        if truth is not None:
            self.truth_s = truth.images["S"]  # the comparison figure shows it beside the methods
        dark = p.dark_offset_dn
        if dark is None:
            dark = float(truth.metrics.get("dark_offset_dn", 0.0)) if truth is not None else 0.0
        free = roi(p.object_free_roi)
        if free is None and truth is not None and np.any(truth.images["S"] <= 1e-9):
            free = truth.images["S"] <= 1e-9
        made = compose(scan.method, {a: rc.result(a) for a in rc.angles}, dark_offset=dark,
                       saturation=rc.saturation, object_free=free, lit_fraction=p.lit_fraction,
                       black_level=p.black_level, p_min=p.p_min, p_rule=p.p_rule,
                       p_model=self.medium.p_model(scan.method, truth, free, dark, rc.saturation, p.p_min,
                                                   crossed=bool(scan.mosaic) and p.mosaic_rule != "global"))
        if made.note:
            self.log.warning("scan %d: %s", scan.scan_id, made.note)
        m = self._metrics(scan, made, truth, dark)
        if (depth := self.depth.run(scan.method, scan.scan_id, dark, rc.saturation, free, truth, p.out)):
            m["depth"] = depth
        self._publish(scan, made, m)
        if p.out:
            write_method(p.out, scan.method, made.image, self.metrics, image_format=p.image_format)
            if p.comparison:
                write_comparison(os.path.join(p.out, "comparison.png"), self.results, self.metrics,
                                 METHOD_NAMES, getattr(self, "truth_s", None), self.depth.publisher.maps)

    def _metrics(self, scan: Scan, made, truth: Composite | None, dark: float) -> dict:
        """The scan's numbers (:func:`~polarstripe.nodes.compositor_scan.scan_metrics`), the chart's bars from
        the params, else from the truth."""
        p = self.params
        m = scan_metrics(scan, made, truth, dark, roi(p.chart_bright_roi), roi(p.chart_dark_roi))
        if scan.mosaic:
            m["mosaic"] = {"layout_deg": scan.mosaic, "rule": p.mosaic_rule}
        if "metrics_error" in m:  # e.g. every bar pixel saturated: no number rather than a wrong one
            self.log.warning("scan %d (%s): %s", scan.scan_id, scan.method, m["metrics_error"])
        return m

    def _publish(self, scan: Scan, made, m: dict) -> None:
        """``compositor/composite`` (and ``compositor/medium_p`` with p), kept for the comparison."""
        image = made.image
        images = {"composite": np.ma.filled(image, 0.0).astype(np.float32),
                  "saturated": np.ma.getmaskarray(image).astype(np.uint8)}
        images.update({k: np.ma.filled(v, 0.0).astype(np.float32) for k, v in made.layers.items()})
        self.composite_pub.publish(Composite(images=images, method=scan.method, scan_id=scan.scan_id,
                                             metrics=m))
        if made.p_estimate is not None:  # the medium's DOP (imaging/p_map.py)
            est = made.p_estimate
            self.estimate_pub.publish(MediumEstimate(p=est.p, scan_id=scan.scan_id,
                                                     p_std=None if np.isnan(est.p_std) else est.p_std))
        self.results[scan.method], self.metrics[scan.method] = image, m
        self.counters["scans_done"] += 1
        self.log.info("scan %d %s: %d frames, contrast %s, error vs truth %s%s", scan.scan_id, scan.method,
                      scan.frames, fmt(m["contrast"]), fmt(m["error_vs_truth"]),
                      f", p {made.p:.3f}" if made.p is not None else "")

NODE = Compositor
