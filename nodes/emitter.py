"""The emitter node: runs scans — sets the analyzer, lights each pattern, has the grabber take each frame.

``emitter/start_scan`` (:class:`~polarstripe.msgs.ScanRequest` → :class:`~polarstripe.msgs.ScanEvent`)
checks the request and answers at once: ``event="start"`` with the new scan id, or ``event="fault"`` naming
what is wrong. The scan then runs in the node's loop, one at a time (requests queue up):

1. ``emitter/scan`` ScanEvent ``start``; the analyzer is put out of the path for unpolarized methods
   (``camera/analyzer``).
2. For each analyzer angle: ``PolarizerCommand`` on ``polarizer/cmd``, then wait until ``polarizer/state``
   is settled at that target (``settle_timeout_s``; a state with a fault ends the scan at once).
3. For each pattern: ``display.show``, ``emitter/pattern``, call ``camera/trigger`` (scan id, step, pattern
   tag) and wait for the matching ``camera/frame`` (``frame_timeout_s``).
4. The display is blanked, the analyzer put back, and ``emitter/scan`` says ``done`` — or ``fault`` with
   ``detail`` naming the step, the topic or service and what happened. A fault never hangs the node.

Methods (:class:`~polarstripe.msgs.Method`): ``flood``, ``polarized_flood`` (flood at E_b and E_w),
``stripes`` (N stripes), ``polarized_stripes`` (N stripes at E_b and E_w), ``hf_separation`` (two
complementary checkers, Nayar et al.'s high-frequency separation). Polarized methods take the analyzer angles of the request: two
angles as given, one angle ``a`` as (a, a + 90), none as the ``analyzer_deg`` param. Unpolarized methods
with angles are taken at those angles; without, with no analyzer (frames carry ``polarizer_deg`` None).

``emitter/show`` (:class:`~polarstripe.msgs.Pattern` → :class:`~polarstripe.msgs.Ack`) lights one pattern
between scans (``polarizer/calibrate`` shows flood through it, then ``off``); refused while a scan runs.

Display backends come from :mod:`polarstripe.nodes.drivers` (``null`` for the simulator and CI, ``window``,
``serial``).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

from polarstripe.msgs import (
    Ack,
    AnalyzerMount,
    Frame,
    FrameRequest,
    Method,
    Pattern,
    PolarizerCommand,
    PolarizerState,
    ScanEvent,
    ScanRequest,
)
from polarstripe.nodes.drivers.errors import DriverError
from polarstripe.nodes.drivers.registry import open_backend
from polarstripe.runtime.bus import BusError, BusTimeout
from polarstripe.runtime.node import Node, NodeStopping
from polarstripe.runtime.params import NodeParams


class ScanFault(Exception):
    """A scan step failed; the text is the ScanEvent's ``detail``."""


@dataclass(frozen=True)
class ScanPlan:
    """A checked scan: its id, method, the pattern tags in order and the analyzer angles (None: out)."""

    scan_id: int
    method: str
    patterns: tuple[str, ...]
    angles: tuple[float | None, ...]
    stripes: int = 0


def plan_scan(req: ScanRequest, scan_id: int, *, default_stripes: int, checker_size: int,
              default_analyzer_deg: list[float]) -> ScanPlan:
    """Check ``req`` and spell out the scan; raises ``ValueError`` naming the field and the value."""
    method = Method.parse(req.method)
    polarized, family = method.polarized, method.family
    stripes = req.stripes or default_stripes
    if family == "stripe" and not 1 <= stripes <= 4096:
        raise ValueError(f"stripes={req.stripes} must be 1..4096")
    angles = [float(a) for a in req.analyzer_deg]
    if any(not math.isfinite(a) for a in angles):
        raise ValueError(f"analyzer_deg={req.analyzer_deg} must be finite angles")
    if polarized:
        angles = angles or [float(a) for a in default_analyzer_deg]
        if len(angles) == 1:
            angles = [angles[0], angles[0] + 90.0]
        if len(angles) != 2:
            raise ValueError(f"method {req.method!r} needs analyzer_deg [E_b, E_w] (or one angle, "
                             f"E_w = E_b + 90), got {req.analyzer_deg}")
    resolved: tuple[float | None, ...] = tuple(angles) if angles else (None,)
    patterns = tuple(str(p) for p in method.patterns(stripes, checker_size))
    return ScanPlan(scan_id, req.method, patterns, resolved, stripes if family == "stripe" else 0)


class Emitter(Node):
    """Runs scans (see the module docstring)."""

    class Params(NodeParams):
        display: str = "null"  # display backend: null | window | serial
        display_width: int = 1024  # projector size [px] (pattern semantics)
        display_height: int = 768
        display_port: str = ""  # serial: the trigger box's port
        display_index: int = 0  # window: which screen
        stripes: int = 30  # when the request says 0
        checker_size: int = 16  # hf_separation checker squares [projector px]
        analyzer_deg: list[float] = []  # polarized methods without angles in the request: [E_b, E_w]
        settle_timeout_s: float = 10.0  # the analyzer must settle within this
        trigger_timeout_s: float = 15.0  # camera/trigger must answer within this
        frame_timeout_s: float = 5.0  # the frame must arrive within this after the trigger's reply
        settle_tolerance_deg: float = 0.05
        max_queued: int = 8

        def validate(self):
            super().validate()
            for key in ("settle_timeout_s", "trigger_timeout_s", "frame_timeout_s"):
                if not getattr(self, key) > 0:
                    raise ValueError(f"{key} must be > 0, got {getattr(self, key)}")
            if self.stripes < 1 or self.checker_size < 1:
                raise ValueError(f"stripes={self.stripes} and checker_size={self.checker_size} must be >= 1")

    PUBLISHES = {"emitter/pattern": Pattern, "emitter/scan": ScanEvent, "polarizer/cmd": PolarizerCommand}
    SUBSCRIBES = {"polarizer/state": PolarizerState, "camera/frame": Frame}
    SERVES = {"emitter/start_scan": (ScanRequest, ScanEvent), "emitter/show": (Pattern, Ack)}

    def setup(self):
        p = self.params
        self.pattern_pub = self.publisher("emitter/pattern")
        self.scan_pub = self.publisher("emitter/scan")
        self.cmd_pub = self.publisher("polarizer/cmd")
        self.subscribe("polarizer/state", mode="latest")
        self.subscribe("camera/frame", mode="all")
        self.serve("emitter/start_scan", self.start_scan)
        self.serve("emitter/show", self.show)
        self.trigger = self.client("camera/trigger", FrameRequest, Ack, timeout_s=p.trigger_timeout_s)
        self.mount = self.client("camera/analyzer", AnalyzerMount, Ack, timeout_s=p.trigger_timeout_s)
        kwargs: dict = {"width": p.display_width, "height": p.display_height}
        if p.display == "serial":
            kwargs["port"] = p.display_port
        elif p.display == "window":
            kwargs["display_index"] = p.display_index
        self.display = open_backend("display", p.display, **kwargs)
        self.queue: deque[ScanPlan] = deque()
        self.next_id = 1
        self.results: dict[int, ScanEvent] = {}
        self.scanning: ScanPlan | None = None  # the scan being run
        self.every(0.01, self.run_queued, name="scan")

    def teardown(self):
        self.display.close()

    # ---- service -------------------------------------------------------------------------------------------
    def start_scan(self, req: ScanRequest) -> ScanEvent:
        p = self.params
        if len(self.queue) >= p.max_queued:
            return ScanEvent(scan_id=0, event="fault", method=req.method,
                             detail=f"emitter/start_scan: {len(self.queue)} scans already queued")
        try:
            plan = plan_scan(req, self.next_id, default_stripes=p.stripes, checker_size=p.checker_size,
                             default_analyzer_deg=p.analyzer_deg)
        except ValueError as exc:
            return ScanEvent(scan_id=0, event="fault", method=req.method, detail=f"emitter/start_scan: {exc}")
        self.next_id += 1
        self.queue.append(plan)
        return self._event(plan, "start")

    def show(self, req: Pattern) -> Ack:
        """``emitter/show``: light one pattern between scans (e.g. flood for ``polarizer/calibrate``, then
        ``off``); published on ``emitter/pattern`` as given. Refused while a scan runs or is queued."""
        if self.scanning is not None or self.queue:
            busy = self.scanning.scan_id if self.scanning is not None else self.queue[0].scan_id
            return Ack(ok=False, detail=f"emitter/show: scan {busy} is running or queued")
        try:
            if req.kind == "off":
                self.display.blank()
            else:
                self.display.show(req)
        except DriverError as exc:  # DriverValueError too: a pattern the display cannot light
            return Ack(ok=False, detail=f"emitter/show: {req.kind}: {exc}")
        self.pattern_pub.publish(req)
        return Ack(ok=True, detail=f"showing {req.kind}")

    def _event(self, plan: ScanPlan, event: str, detail: str = "") -> ScanEvent:
        return ScanEvent(scan_id=plan.scan_id, event=event, method=plan.method, stripes=plan.stripes,
                         analyzer_deg=[a for a in plan.angles if a is not None], detail=detail)

    # ---- the scan ------------------------------------------------------------------------------------------
    def run_queued(self) -> None:
        while self.queue and not self.stopping:
            self.scanning = self.queue.popleft()
            try:
                self.run_scan(self.scanning)
            finally:
                self.scanning = None

    def run_scan(self, plan: ScanPlan) -> ScanEvent:
        """Run one scan to its end; publish and return its final event (done or fault)."""
        self.scan_pub.publish(self._event(plan, "start"))
        self.log.info("scan %d (%s): %d patterns x %d analyzer angles", plan.scan_id, plan.method,
                      len(plan.patterns), len(plan.angles))
        unpolarized = plan.angles == (None,)
        self.timing = {"analyzer_s": 0.0, "camera_s": 0.0, "frame_wait_s": 0.0, "frames": 0}
        t_scan = time.monotonic()
        try:
            if unpolarized:
                self._mount(False)
            step = 0
            for angle in plan.angles:
                if angle is not None:
                    t0 = time.monotonic()
                    self._set_analyzer(angle)
                    self.timing["analyzer_s"] += time.monotonic() - t0
                for tag in plan.patterns:
                    if self.stopping:
                        raise ScanFault(f"stopped ({self._stop_reason})")
                    self._take(plan, tag, step)
                    step += 1
            final = self._event(plan, "done")
        except ScanFault as exc:
            final = self._event(plan, "fault", str(exc))
            self.log.error("scan %d (%s) fault: %s", plan.scan_id, plan.method, exc)
        finally:
            try:
                self.display.blank()
            except DriverError as exc:
                self.log.error("display: %s", exc)
            if unpolarized:
                try:
                    self._mount(True)
                except ScanFault as exc:
                    self.log.error("%s", exc)
        self.scan_pub.publish(final)
        self.results[plan.scan_id] = final
        if final.event == "done":
            t = self.timing
            self.log.info("scan %d (%s) done in %.3f s: %d frames, analyzer %.3f s, camera %.3f s, "
                          "frame wait %.3f s", plan.scan_id, plan.method, time.monotonic() - t_scan,
                          t["frames"], t["analyzer_s"], t["camera_s"], t["frame_wait_s"])
        return final

    def _mount(self, inserted: bool) -> None:
        try:
            ack = self.mount.call(AnalyzerMount(inserted=inserted))
        except (BusError, TimeoutError) as exc:
            raise ScanFault(f"camera/analyzer: {exc}") from None
        if not ack.ok:
            raise ScanFault(f"camera/analyzer: {ack.detail}")

    def _set_analyzer(self, angle: float) -> None:
        tol = self.params.settle_tolerance_deg
        self.cmd_pub.publish(PolarizerCommand(target_deg=angle))

        def settled_or_faulted(s: PolarizerState) -> bool:
            return bool(s.fault) or (s.settled and abs(s.target_deg - angle) <= tol
                                     and abs(s.angle_deg - angle) <= tol)

        try:
            state = self.wait_for("polarizer/state", settled_or_faulted, self.params.settle_timeout_s)
        except BusTimeout:
            raise ScanFault(f"polarizer/state: analyzer not settled at {angle:g} deg within "
                            f"{self.params.settle_timeout_s:g} s") from None
        except NodeStopping as exc:
            raise ScanFault(f"stopped ({exc.reason}) waiting for polarizer/state") from None
        if state.fault:
            raise ScanFault(f"polarizer/state: fault at {state.angle_deg:g} deg: {state.fault}")

    def _take(self, plan: ScanPlan, tag: str, step: int) -> None:
        where = f"step {step} ({tag})"
        try:
            self.display.show(tag)
        except DriverError as exc:
            raise ScanFault(f"{where}: display: {exc}") from None
        self.pattern_pub.publish(Pattern.of(tag, plan.scan_id, step))
        t0 = time.monotonic()
        try:
            ack = self.trigger.call(FrameRequest(scan_id=plan.scan_id, step=step, pattern=tag))
        except (BusError, TimeoutError) as exc:
            raise ScanFault(f"{where}: camera/trigger: {exc}") from None
        if not ack.ok:
            raise ScanFault(f"{where}: camera/trigger: {ack.detail}")
        t1 = time.monotonic()
        try:
            self.wait_for("camera/frame", lambda f: (f.scan_id, f.step) == (plan.scan_id, step),
                          self.params.frame_timeout_s)
        except BusTimeout:
            raise ScanFault(f"{where}: camera/frame: no frame within {self.params.frame_timeout_s:g} s "
                            "after the trigger") from None
        except NodeStopping as exc:
            raise ScanFault(f"{where}: stopped ({exc.reason}) waiting for camera/frame") from None
        self.timing["camera_s"] += t1 - t0
        self.timing["frame_wait_s"] += time.monotonic() - t1
        self.timing["frames"] += 1


NODE = "Emitter"
