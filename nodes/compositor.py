"""The compositor node: folds each scan's frames into running reductions and, when the scan is done, makes the
method's composite, scores it and writes it out.

* subscribes ``camera/frame`` and ``emitter/scan`` (every message, frames first in each poll);
* per scan, a :class:`~polarstripe.imaging.composite.RunningComposite` keeps one per-pixel max and min per
  analyzer angle (buffers reused from scan to scan): memory does not grow with the number of stripes;
* on "done" it makes the composite of the scan's method (dark offset subtracted, saturated pixels masked):
  ``flood`` the frame; ``polarized_flood`` eq. 6 on the two analyzer frames with p estimated over an
  object-free region; ``stripes`` the max composite (eq. 7); ``polarized_stripes`` the max composites at E_b
  and E_w, then eq. 6; ``hf_separation`` the direct image from the max and min over the complementary checkers
  (Nayar et al. 2006). E_b is whichever analyzer angle passes less light over the object-free region;
* scores it: Michelson contrast over the chart's bright and dark bars, and ``error_vs_truth`` (relative RMS,
  gain fitted) against the simulator's ground truth: the newest ``simulator/truth`` message (the simulator
  publishes it at every scan start, so a recording carries it), else the ``simulator/truth`` service when a
  node serves it, else none (contrast only, with bar and object-free regions from params);
* publishes ``compositor/composite`` (images ``composite`` float32 DN, 0 where masked, and ``saturated``
  uint8; ``e_b``/``e_w`` or ``global`` where the method has them) and, after a polarized method,
  ``medium/estimate`` (p; σ_t is not estimated);
* writes ``<out>/<method>.png`` (16-bit DN, clipped), ``<out>/<method>.tiff`` (float32 DN, NaN where masked;
  ``.npy`` with ``image_format = "npy"``), ``<out>/metrics.json`` (method → metrics, rewritten after every
  scan) and ``<out>/comparison.png`` (the methods side by side, like the paper's Fig. 6).

Calibration frames of the polarizer (scan ids from 2**30) are ignored. Frames that do not belong are dropped
and counted (heartbeat counters ``frames_unexpected`` no scan running,
``frames_mismatched`` another scan id, ``frames_bad`` shape/dtype/ndim, ``frames_duplicate`` a step seen
twice, ``frames_bad_pattern`` a pattern the method does not use, ``frames_bad_angle`` an analyzer angle not in
the scan).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.imaging.composite import RunningComposite
from polarstripe.imaging.metrics import michelson_contrast, signal_error
from polarstripe.imaging.polarization import estimate_p, recover_signal
from polarstripe.imaging.separation import separate_direct_global
from polarstripe.imaging.validation import ImagingError, roi_slices
from polarstripe.msgs import (
    CALIBRATION_SCAN_ID,
    METHOD_NAMES,
    Composite,
    Empty,
    Frame,
    MediumEstimate,
    MessageError,
    Method,
    ScanEvent,
)
from polarstripe.nodes.compositor_output import write_comparison, write_method
from polarstripe.runtime.bus import BusError
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams

_DROPS = ("frames_unexpected", "frames_mismatched", "frames_bad", "frames_duplicate", "frames_bad_pattern",
          "frames_bad_angle")


def _roi(values: list[int]):
    return tuple(values) if values else None


@dataclass
class _Scan:
    scan_id: int
    method: str
    stripes: int
    analyzer_deg: list[float]
    steps: set[int] = field(default_factory=set)
    frames: int = 0
    dropped: int = 0
    bit_depth: int = 12


class Compositor(Node):
    """Running reductions per scan, the method's composite, its metrics and files (module docstring)."""

    class Params(NodeParams):
        out: str = ""  # output folder; "" = publish only
        dark_offset_dn: float | None = None  # None: the simulator truth's, else 0
        saturation_dn: float | None = None  # None: 2**bit_depth - 1 of the frames
        angle_tolerance_deg: float = 2.0  # a frame's analyzer angle vs the scan's angles
        object_free_roi: list[int] = []  # (row0, row1, col0, col1) for p; empty: from truth, else whole frame
        chart_bright_roi: list[int] = []  # bright bars (row0, row1, col0, col1); empty: from truth
        chart_dark_roi: list[int] = []  # dark bars
        lit_fraction: float = 0.5  # of the checker patterns
        black_level: float = 0.0  # projector "off" relative to "on"
        p_min: float = 0.05
        use_truth: bool = True  # ask simulator/truth when a node of the launch serves it
        truth_timeout_s: float = 10.0
        truth_wait_s: float = 1.0  # without a service, wait this long for the scan's simulator/truth message
        done_grace_s: float = 0.3  # after "done", wait this long for frames still in flight
        image_format: Literal["tiff", "npy"] = "tiff"
        comparison: bool = True

        def validate(self):
            super().validate()
            for key in ("object_free_roi", "chart_bright_roi", "chart_dark_roi"):
                if getattr(self, key) and len(getattr(self, key)) != 4:
                    raise ValueError(f"{key} must be [row0, row1, col0, col1], got {getattr(self, key)}")
            if bool(self.chart_bright_roi) != bool(self.chart_dark_roi):
                raise ValueError("give both chart_bright_roi and chart_dark_roi, or neither")

    PUBLISHES = {"compositor/composite": Composite, "medium/estimate": MediumEstimate}
    SUBSCRIBES = {"camera/frame": Frame, "emitter/scan": ScanEvent, "simulator/truth": Composite}

    def setup(self):
        self.scan: _Scan | None = None
        self.running = None  # RunningComposite, reused across scans of one shape and dtype
        self.results: dict[str, np.ma.MaskedArray] = {}  # the last composite of each method
        self.metrics: dict[str, dict] = {}
        self._truth_client = None
        self._draining = False
        self._truth_served = self.params.use_truth
        for key in (*_DROPS, "frames_calibration", "scans_done", "scans_failed"):
            self.counters[key] = 0
        self.composite_pub = self.publisher("compositor/composite")
        self.estimate_pub = self.publisher("medium/estimate")
        self.subscribe("camera/frame", self.on_frame, mode="all")
        self.subscribe("emitter/scan", self.on_scan, mode="all")
        self.topic_truth: Composite | None = None  # the newest simulator/truth message
        self._truth_fresh = False  # one came since the running scan's start
        self._truth_heard = self._truth_silent = False
        if self.params.use_truth:
            self.subscribe("simulator/truth", self.on_truth, mode="latest")
        if self.params.out:
            os.makedirs(self.params.out, exist_ok=True)
            path = os.path.join(self.params.out, "metrics.json")
            if os.path.exists(path):
                with open(path) as f:
                    self.metrics = json.load(f)

    # ---- frames ----------------------------------------------------------------------------------------
    def _drop(self, why: str, frame: Frame, detail: str = "") -> None:
        self.counters[why] += 1
        if self.scan is not None and frame.scan_id == self.scan.scan_id:
            self.scan.dropped += 1
        n = self.counters[why]
        if n <= 3 or n % 100 == 0:
            self.log.warning("dropped frame (scan %d step %d): %s%s (%d so far)", frame.scan_id,
                             frame.step, why.removeprefix("frames_").replace("_", " "),
                             f": {detail}" if detail else "", n)

    def on_frame(self, frame: Frame) -> None:

        if frame.scan_id >= CALIBRATION_SCAN_ID:
            self.counters["frames_calibration"] += 1  # the polarizer's, not a scan's
            return

        if (self.scan is None or frame.scan_id != self.scan.scan_id) and not self._draining:
            self._catch_up()  # scan events come on another socket: a "start" may wait behind the frames
        scan = self.scan
        if scan is None:
            return self._drop("frames_unexpected", frame, "no scan running")
        if frame.scan_id != scan.scan_id:
            return self._drop("frames_mismatched", frame, f"the running scan is {scan.scan_id}")
        image = frame.image
        if image.ndim != 2 or image.dtype.kind not in "uif" or image.size == 0:
            return self._drop("frames_bad", frame, f"image {image.dtype} {image.shape}")
        if frame.step in scan.steps:
            return self._drop("frames_duplicate", frame)
        if not Method(scan.method).accepts(frame.pattern):
            return self._drop("frames_bad_pattern", frame, f"{frame.pattern!r} in a {scan.method} scan")
        key = self._angle_key(frame.polarizer_deg, scan)
        if key is False:
            return self._drop("frames_bad_angle", frame, f"{frame.polarizer_deg} not in {scan.analyzer_deg}")
        rc = self.running
        if scan.frames == 0 and (rc is None or rc.shape != image.shape or rc.dtype != image.dtype):
            sat = self.params.saturation_dn
            sat = float((1 << frame.bit_depth) - 1) if sat is None and image.dtype.kind in "ui" else sat
            rc = self.running = RunningComposite(image.shape, image.dtype, saturation=sat)
        elif rc.shape != image.shape or rc.dtype != image.dtype:
            return self._drop("frames_bad", frame,
                              f"{image.dtype} {image.shape}, scan has {rc.dtype} {rc.shape}")
        rc.add(image, key)
        scan.steps.add(frame.step)
        scan.frames += 1
        scan.bit_depth = frame.bit_depth

    def _take(self, topic: str, timeout_s: float) -> list:
        """Every message already arrived on ``topic`` (waiting up to ``timeout_s`` for the first). Unlike
        :meth:`Node.wait_for`, which keeps one message of what it takes, nothing is dropped."""

        out = []
        for item in self._bus.take(self._subs[topic].source, timeout_s):
            if isinstance(item, MessageError):
                self._bad(topic, item)
            else:
                out.append(item)
        return out

    def _catch_up(self) -> None:
        """Handle the scan events that have already arrived, before judging a frame."""
        while events := self._take("emitter/scan", 0.0):
            for ev in events:
                self.on_scan(ev)

    def _angle_key(self, angle: float | None, scan: _Scan):
        """The scan's nominal analyzer angle nearest ``angle`` (modulo 180), None without one, or False."""
        if not scan.analyzer_deg:
            return None
        if angle is None or not math.isfinite(angle):
            return False
        dist = [abs((angle - a + 90.0) % 180.0 - 90.0) for a in scan.analyzer_deg]
        i = int(np.argmin(dist))
        return scan.analyzer_deg[i] if dist[i] <= self.params.angle_tolerance_deg else False

    # ---- scans -----------------------------------------------------------------------------------------
    def on_scan(self, ev: ScanEvent) -> None:
        if ev.event == "start":
            if self.scan is not None:
                self.log.warning("scan %d started before scan %d ended: the old one is dropped", ev.scan_id,
                                 self.scan.scan_id)
            if ev.method not in METHOD_NAMES:
                self.log.error("scan %d: unknown method %r (known: %s)", ev.scan_id, ev.method,
                               ", ".join(METHOD_NAMES))
                self.scan = None
                return
            self.scan = _Scan(ev.scan_id, ev.method, ev.stripes, [float(a) for a in ev.analyzer_deg])
            # the simulator publishes the truth of this scan after its start (it may be handled first)
            t = self.topic_truth
            self._truth_fresh = t is not None and t.header.stamp_ns >= ev.header.stamp_ns
            if self.running is not None:
                self.running.reset()
        elif self.scan is None or ev.scan_id != self.scan.scan_id:
            self.log.warning("scan %d %s: not the running scan", ev.scan_id, ev.event)
        elif ev.event == "fault":
            self.log.error("scan %d (%s) ended on a fault: %s", ev.scan_id, self.scan.method, ev.detail)
            self.counters["scans_failed"] += 1
            self.scan = None
        else:
            scan, self.scan = self.scan, None
            self._drain(scan)
            try:
                self.finish(scan)
            except PolarstripeError as exc:  # published, so that nobody waits for a composite in vain
                self.counters["scans_failed"] += 1
                self.log.error("scan %d (%s): no composite: %s", scan.scan_id, scan.method, exc)
                self.composite_pub.publish(Composite(images={}, method=scan.method, scan_id=scan.scan_id,
                                                     metrics={"error": str(exc), "frames": scan.frames}))

    def _drain(self, scan: _Scan) -> None:
        """Take frames of ``scan`` still in flight when "done" arrived (they come on another socket)."""
        n_angles = max(1, len(scan.analyzer_deg))
        expected = {"stripes": scan.stripes * n_angles, "polarized_stripes": scan.stripes * n_angles,
                    "hf_separation": None}.get(scan.method, n_angles)
        self.scan, self._draining = scan, True
        try:
            while expected is None or scan.frames + scan.dropped < expected:
                frames = self._take("camera/frame", self.params.done_grace_s)
                if not frames:
                    if expected is not None:
                        self.log.warning("scan %d: %d of %d frames", scan.scan_id, scan.frames, expected)
                    break
                for frame in frames:
                    self.on_frame(frame)
        finally:
            self.scan, self._draining = None, False

    # ---- the composite ---------------------------------------------------------------------------------
    def on_truth(self, truth: Composite) -> None:
        self.topic_truth, self._truth_fresh, self._truth_heard = truth, True, True

    def _truth(self, shape) -> Composite | None:
        """The ground truth for a scan of frames of ``shape``, in this order: a ``simulator/truth`` message
        that came since the scan's start; the service's answer (live); a message waited for up to
        ``truth_wait_s`` (a replay: it has its own socket and may trail the frames; a silent topic is not
        waited for again); None. A truth of another shape is not used."""
        if not self.params.use_truth:
            return None
        for truth in self._take("simulator/truth", 0.0):  # one that came with the last frames
            self.on_truth(truth)
        if not self._truth_fresh and self._truth_served:
            truth = self._served_truth()
            if truth is not None:
                return self._fits(truth, shape)
        if not self._truth_fresh and not self._truth_silent:
            for truth in self._take("simulator/truth", self.params.truth_wait_s):
                self.on_truth(truth)
            if not self._truth_heard:
                self._truth_silent = True
                self.log.info("no ground truth on simulator/truth within %g s: not waited for again",
                              self.params.truth_wait_s)
        return self._fits(self.topic_truth, shape) if self._truth_fresh else None

    def _fits(self, truth: Composite | None, shape) -> Composite | None:
        if truth is not None and truth.images["S"].shape != shape:
            self.log.warning("truth is %s, frames are %s: not used", truth.images["S"].shape, shape)
            return None
        return truth

    def _served_truth(self) -> Composite | None:
        """The ``simulator/truth`` service's answer, or None (not served: not asked again)."""

        try:
            if self._truth_client is None:
                self._truth_client = self.client("simulator/truth", Empty, Composite,
                                                 timeout_s=self.params.truth_timeout_s)
        except BusError as exc:  # no node of this launch serves it: a real rig, or a replay
            self._truth_served = False
            self.log.info("no simulator/truth service (%s)", exc)
            return None
        try:
            return self._truth_client.call(Empty())
        except BusError as exc:  # a timeout or an error reply: try again next scan
            self.log.warning("no ground truth for this scan: %s", exc)
            return None

    def finish(self, scan: _Scan) -> None:

        if scan.frames == 0:
            raise PolarstripeError("no frames")
        rc = self.running
        truth = self._truth(rc.shape)
        dark = self.params.dark_offset_dn
        if dark is None:
            dark = float(truth.metrics.get("dark_offset_dn", 0.0)) if truth is not None else 0.0
        free = _roi(self.params.object_free_roi)
        if free is None and truth is not None and np.any(truth.images["S"] <= 1e-9):
            free = truth.images["S"] <= 1e-9
        image, extra, p = self._compose(scan, rc, dark, free)
        bright, dim = _roi(self.params.chart_bright_roi), _roi(self.params.chart_dark_roi)
        if bright is None and truth is not None:
            band, high = truth.images["chart_band"], truth.images["chart_high"]
            if np.any((band >= 0) & high) and np.any((band >= 0) & ~high):
                bright, dim = (band >= 0) & high, (band >= 0) & ~high
        m = {"scan_id": scan.scan_id, "frames": scan.frames, "frames_dropped": scan.dropped,
             "stripes": scan.stripes, "analyzer_deg": scan.analyzer_deg, "dark_offset_dn": dark,
             "saturated_pixels": int(np.ma.count_masked(image)), "contrast": None, "error_vs_truth": None}
        if p is not None:
            m["p"] = p
        try:
            if bright is not None:
                m["contrast"] = michelson_contrast(image, bright, dim)
            if truth is not None:
                m["error_vs_truth"] = signal_error(image, truth.images["S"], fit_gain=True)
        except ImagingError as exc:  # e.g. every bar pixel saturated: no number rather than a wrong one
            m["metrics_error"] = str(exc)
            self.log.warning("scan %d (%s): %s", scan.scan_id, scan.method, exc)
        images = {"composite": np.ma.filled(image, 0.0).astype(np.float32),
                  "saturated": np.ma.getmaskarray(image).astype(np.uint8)}
        images.update({k: np.ma.filled(v, 0.0).astype(np.float32) for k, v in extra.items()})
        self.composite_pub.publish(Composite(images=images, method=scan.method, scan_id=scan.scan_id,
                                             metrics=m))
        if p is not None:
            self.estimate_pub.publish(MediumEstimate(p=p, scan_id=scan.scan_id))
        self.results[scan.method], self.metrics[scan.method] = image, m
        self.counters["scans_done"] += 1
        self.log.info("scan %d %s: %d frames, contrast %s, error vs truth %s%s", scan.scan_id, scan.method,
                      scan.frames, _fmt(m["contrast"]), _fmt(m["error_vs_truth"]),
                      f", p {p:.3f}" if p is not None else "")
        if self.params.out:
            self._write(scan.method, image)

    def _compose(self, scan: _Scan, rc, dark: float, free):
        """(composite, extra images, p or None) for the scan's method; DN above the dark offset, masked."""

        angles = rc.angles
        method = scan.method
        if method in ("polarized_flood", "polarized_stripes"):
            if len(angles) != 2:
                raise PolarstripeError(f"{method} needs frames at two analyzer angles, got {angles}")
            a, b = (rc.result(x).maximum for x in angles)
            region = roi_slices("object_free_roi", free, rc.shape)
            if np.ma.median(a[region]) > np.ma.median(b[region]):
                a, b = b, a  # E_b passes less backscatter
            e_b, e_w = a.astype(np.float64) - dark, b.astype(np.float64) - dark
            try:
                p = estimate_p(a.data, b.data, free, dark_offset=dark, saturation=rc.saturation,
                               p_min=self.params.p_min)
            except ImagingError as exc:  # no usable object-free pixels: the crossed frame, unrecovered
                self.log.warning("scan %d: p not estimated (%s): the composite is E_b without eq. 6",
                                 scan.scan_id, exc)
                return e_b, {"e_b": e_b, "e_w": e_w}, None
            return recover_signal(e_b, e_w, p), {"e_b": e_b, "e_w": e_w}, p
        result = rc.result(angles[0])
        if method == "hf_separation":
            direct, glob = separate_direct_global(result.maximum.astype(np.float64) - dark,
                                                  result.minimum.astype(np.float64) - dark,
                                                  lit_fraction=self.params.lit_fraction,
                                                  black_level=self.params.black_level)
            return direct, {"global": glob}, None
        return result.maximum.astype(np.float64) - dark, {}, None  # flood: the frame; stripes: eq. 7

    # ---- files -----------------------------------------------------------------------------------------
    def _write(self, method: str, image: np.ma.MaskedArray) -> None:

        out = self.params.out
        write_method(out, method, image, self.metrics, image_format=self.params.image_format)
        if self.params.comparison:
            write_comparison(os.path.join(out, "comparison.png"), self.results, self.metrics, METHOD_NAMES)


def _fmt(x) -> str:
    return "n/a" if x is None else f"{x:.3f}"


NODE = Compositor
