"""The emitter node: runs scans — sets the analyzer, lights each pattern, has the grabber take each frame.

``emitter/start_scan`` (:class:`~polarstripe.msgs.ScanRequest` → :class:`~polarstripe.msgs.ScanEvent`)
checks the request and answers at once: ``event="start"`` with the new scan id, or ``event="fault"`` naming
what is wrong. Scans run one at a time, in request order (at most ``max_queued`` wait):

1. ``emitter/scan`` ScanEvent ``start``; the analyzer is put out of the path for unpolarized methods
   (``camera/analyzer``).
2. For each analyzer angle: ``PolarizerCommand`` on ``polarizer/cmd``, then wait until ``polarizer/state``
   is settled at that target (``settle_timeout_s``; a state with a fault ends the scan at once).
3. For each pattern: ``display.show``, ``emitter/pattern``, call ``camera/trigger`` (scan id, step, pattern
   tag; bounded by ``trigger_timeout_s``) and wait for the matching ``camera/frame`` (``frame_timeout_s``).
4. The display is blanked, the analyzer put back, and ``emitter/scan`` says ``done`` — or ``fault`` with
   ``detail`` naming the step, the topic or service and what happened. A fault never hangs the node.

**A scan is a state machine stepped by the node's loop**, not a loop inside one handler: the ``scan`` timer
(every 10 ms) starts the next queued scan and enforces the timeouts; a ``polarizer/state`` or
``camera/frame`` that the scan waits for moves it on. Between those events the loop answers services, so
``emitter/show`` is refused at once while a scan runs (``scan N running``), ``emitter/start_scan`` queues
another, and a stop (SIGINT, SIGTERM) ends the running scan with a published ``fault`` (``stopped (SIGTERM)
waiting for camera/frame``), the display blanked and the analyzer put back. The one blocking step is the
``camera/trigger`` call (the grabber answers once the frame is taken), bounded by ``trigger_timeout_s``.

Methods (:class:`~polarstripe.msgs.Method`): ``flood``, ``polarized_flood`` (flood at E_b and E_w),
``stripes`` (N stripes), ``polarized_stripes`` (N stripes at E_b and E_w; with K sheets per frame, the
request's ``sheets`` or the ``sheets`` param, ⌈N/K⌉ frames ``stripe:I/N:xK`` per angle),
``hf_separation`` (two
complementary checkers, Nayar et al.'s high-frequency separation). Polarized methods take the analyzer
angles of the request: two angles as given, one angle ``a`` as (a, a + 90), none as the ``analyzer_deg``
param. Unpolarized methods with angles are taken at those angles; without, with no analyzer (frames carry
``polarizer_deg`` None). With ``analyzer = "mosaic"`` (a polarization camera, ``camera = "sim_polarization"``
in the grabber) every method is one pass of its patterns with no analyzer command and no
``camera/analyzer`` call, its ``emitter/scan`` events give no angles, and each frame holds E_b and E_w
(the compositor demosaics it): a polarized stripe scan takes N frames instead of 2N and no stage move.

Scan ids count from 1 and never repeat within a launch: the next id is kept in the run directory
(``state/emitter.json``, runtime/liveness.py), so a respawned emitter goes on from where the last one stopped.

``emitter/show`` (:class:`~polarstripe.msgs.Pattern` → :class:`~polarstripe.msgs.Ack`) lights one pattern
between scans (``polarizer/calibrate`` shows flood through it, then ``off``); refused while a scan runs or
waits.

The display is a backend of :mod:`polarstripe.nodes.drivers` (``null`` for the simulator and CI,
``window``, ``serial``, or an entry point's), named by ``display`` and made from ``display_options`` (the
backend's own ``Options``, the projector's size among them: docs/nodes.md).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Literal

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
from polarstripe.nodes.drivers.registry import check_backend, open_backend
from polarstripe.runtime.bus import BusError
from polarstripe.runtime.liveness import RunState
from polarstripe.runtime.node import Node
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
    sheets: int = 1


def plan_scan(req: ScanRequest, scan_id: int, *, default_stripes: int, checker_size: int,
              default_analyzer_deg: list[float], mosaic: bool = False, default_sheets: int = 1) -> ScanPlan:
    """Check ``req`` and spell out the scan; raises ``ValueError`` naming the field and the value. With a
    polarization camera (``mosaic``) every method is one pass with no analyzer angle: each frame holds E_b
    and E_w."""
    method = Method.parse(req.method)
    polarized, family = method.polarized and not mosaic, method.family
    stripes = req.stripes or default_stripes
    if family == "stripe" and not 1 <= stripes <= 4096:
        raise ValueError(f"stripes={req.stripes} must be 1..4096")
    sheets = (req.sheets or default_sheets) if family == "stripe" else 1
    if not 1 <= sheets <= stripes:
        raise ValueError(f"sheets={sheets} must be 1..stripes ({stripes})")
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
    resolved: tuple[float | None, ...] = tuple(angles) if angles and not mosaic else (None,)
    patterns = tuple(str(p) for p in method.patterns(stripes, checker_size, sheets))
    return ScanPlan(scan_id, req.method, patterns, resolved, stripes if family == "stripe" else 0, sheets)


@dataclass
class _Run:
    """The scan being run: the next step, what it waits for and until when."""

    plan: ScanPlan
    requested_s: float  # when it was asked for (node clock)
    started_s: float
    step: int = 0  # the next frame to take: angle index * len(patterns) + pattern index
    settled: int = -1  # the angle index the analyzer is known settled at
    waiting: str = ""  # "polarizer/state" | "camera/frame" | "" (between steps)
    angle: float | None = None  # the angle being settled at
    deadline: float = math.inf
    since: float = 0.0  # when the wait began
    timing: dict = field(default_factory=lambda: {"analyzer_s": 0.0, "camera_s": 0.0, "frame_wait_s": 0.0,
                                                  "frames": 0})

    @property
    def unpolarized(self) -> bool:
        return self.plan.angles == (None,)

    def where(self) -> str:
        tag = self.plan.patterns[self.step % len(self.plan.patterns)]
        return f"step {self.step} ({tag})"


class Emitter(Node):
    """Runs scans as a state machine stepped by the loop (see the module docstring)."""

    class Params(NodeParams):
        display: str = "null"  # display backend: null | window | serial, or an entry point's
        display_options: dict[str, Any] = {}  # the backend's own options (its Options)
        stripes: int = 30  # when the request says 0
        sheets: int = 1  # light sheets per stripe frame when the request says 0 (stripe:I/N:xK)
        checker_size: int = 16  # hf_separation checker squares [projector px]
        analyzer_deg: list[float] = []  # polarized methods without angles in the request: [E_b, E_w]
        settle_timeout_s: float = 10.0  # the analyzer must settle within this
        trigger_timeout_s: float = 15.0  # camera/trigger must answer within this
        frame_timeout_s: float = 5.0  # the frame must arrive within this after the trigger's reply
        settle_tolerance_deg: float = 0.05
        max_queued: int = 8
        analyzer: Literal["stage", "mosaic"] = "stage"  # stage: a rotating analyzer; mosaic: a polarization
        # camera's micro-polarizers (no analyzer moves or mounts, one pass per scan)

        def validate(self):
            super().validate()
            check_backend("display", self.display, self.display_options)
            for key in ("settle_timeout_s", "trigger_timeout_s", "frame_timeout_s"):
                if not getattr(self, key) > 0:
                    raise ValueError(f"{key} must be > 0, got {getattr(self, key)}")
            if self.stripes < 1 or self.checker_size < 1:
                raise ValueError(f"stripes={self.stripes} and checker_size={self.checker_size} must be >= 1")
            if not 1 <= self.sheets <= self.stripes:
                raise ValueError(f"sheets={self.sheets} must be 1..stripes ({self.stripes})")

    PUBLISHES = {"emitter/pattern": Pattern, "emitter/scan": ScanEvent, "polarizer/cmd": PolarizerCommand}
    SUBSCRIBES = {"polarizer/state": PolarizerState, "camera/frame": Frame}
    SERVES = {"emitter/start_scan": (ScanRequest, ScanEvent), "emitter/show": (Pattern, Ack)}

    def setup(self):
        p = self.params
        self.pattern_pub = self.publisher("emitter/pattern")
        self.scan_pub = self.publisher("emitter/scan")
        self.cmd_pub = self.publisher("polarizer/cmd")
        self.subscribe("polarizer/state", self.on_state, mode="latest")
        self.subscribe("camera/frame", self.on_frame, mode="all")
        self.serve("emitter/start_scan", self.start_scan)
        self.serve("emitter/show", self.show)
        self.trigger = self.client("camera/trigger", FrameRequest, Ack, timeout_s=p.trigger_timeout_s)
        self.mount = self.client("camera/analyzer", AnalyzerMount, Ack, timeout_s=p.trigger_timeout_s)
        self.display = open_backend("display", p.display, p.display_options)
        self.queue: deque[tuple[ScanPlan, float]] = deque()  # (plan, when requested)
        # scan ids never repeat within a launch: the next one is kept in the run directory, so a respawned
        # emitter goes on from there (runtime/liveness.py)
        self.run_state = RunState.of(self.graph, self.name)
        self.next_id = int(self.run_state.get("next_scan_id", 1))
        if self.next_id > 1:
            self.log.info("incarnation %d: scan ids go on from %d", self.incarnation, self.next_id)
        self.current: _Run | None = None  # the scan being run
        self._state: tuple[PolarizerState, float] | None = None  # newest polarizer/state not yet looked at
        self.every(0.01, self.on_tick, name="scan")

    @property
    def scanning(self) -> ScanPlan | None:
        """The scan being run (None between scans)."""
        return self.current.plan if self.current is not None else None

    def teardown(self):
        run = self.current
        if run is not None:  # stopped mid-scan: its fault is published, the rig left as between scans
            what = f" waiting for {run.waiting}" if run.waiting else ""
            where = f"{run.where()}: " if run.waiting == "camera/frame" else ""
            self._fail(f"{where}stopped ({self.stop_reason}){what}")
        self.display.close()

    # ---- services ------------------------------------------------------------------------------------------
    def start_scan(self, req: ScanRequest) -> ScanEvent:
        p = self.params
        if len(self.queue) >= p.max_queued:
            return ScanEvent(scan_id=0, event="fault", method=req.method,
                             detail=f"emitter/start_scan: {len(self.queue)} scans already queued")
        try:
            plan = plan_scan(req, self.next_id, default_stripes=p.stripes, checker_size=p.checker_size,
                             default_analyzer_deg=p.analyzer_deg, mosaic=p.analyzer == "mosaic",
                             default_sheets=p.sheets)
        except ValueError as exc:
            return ScanEvent(scan_id=0, event="fault", method=req.method, detail=f"emitter/start_scan: {exc}")
        self.next_id += 1
        self.run_state.save(next_scan_id=self.next_id)  # before the reply: an id handed out is never reused
        self.queue.append((plan, self.now()))
        return self._event(plan, "start")

    def show(self, req: Pattern) -> Ack:
        """``emitter/show``: light one pattern between scans (e.g. flood for ``polarizer/calibrate``, then
        ``off``); published on ``emitter/pattern`` as given. Refused while a scan runs or is queued."""
        if self.current is not None:
            return Ack(ok=False, detail=f"emitter/show: scan {self.current.plan.scan_id} running")
        if self.queue:
            return Ack(ok=False, detail=f"emitter/show: scan {self.queue[0][0].scan_id} queued")
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
                         analyzer_deg=[a for a in plan.angles if a is not None], detail=detail,
                         sheets=plan.sheets)

    # ---- the events that step a scan ---------------------------------------------------------------------
    def on_tick(self) -> None:
        """Every 10 ms: a wait past its deadline is a fault; between scans, the next queued one starts."""
        run, p = self.current, self.params
        if run is not None:
            if self.now() >= run.deadline:
                if run.waiting == "polarizer/state":
                    text = (f"polarizer/state: analyzer not settled at {run.angle:g} deg within "
                            f"{p.settle_timeout_s:g} s")
                else:
                    text = (f"{run.where()}: camera/frame: no frame within {p.frame_timeout_s:g} s "
                            "after the trigger")
                self._fail(text)
        elif self.queue and not self.stopping:
            self._start(*self.queue.popleft())

    def on_state(self, state: PolarizerState) -> None:
        self._state = (state, self.now())
        run = self.current
        if run is not None and run.waiting == "polarizer/state":
            self._check_settled()

    def on_frame(self, frame: Frame) -> None:
        run = self.current
        if run is None or run.waiting != "camera/frame" or (frame.scan_id, frame.step) != (run.plan.scan_id,
                                                                                           run.step):
            return  # not the frame this scan waits for (a late one of a timed-out step): dropped
        run.timing["frame_wait_s"] += self.now() - run.since
        run.timing["frames"] += 1
        run.step += 1
        self._wait("")
        self._steps()

    # ---- the scan ------------------------------------------------------------------------------------------
    def _start(self, plan: ScanPlan, requested_s: float) -> None:
        self.scan_pub.publish(self._event(plan, "start"))
        self.log.info("scan %d (%s): %d patterns x %d analyzer angles", plan.scan_id, plan.method,
                      len(plan.patterns), len(plan.angles))
        self.current = _Run(plan, requested_s, self.now())
        if self.current.unpolarized and self.params.analyzer == "stage":
            try:
                self._mount(False)
            except ScanFault as exc:
                return self._fail(str(exc))
        self._steps()

    def _steps(self) -> None:
        """Go as far as the scan can without waiting: command the analyzer, or take the next frame."""
        run = self.current
        n = len(run.plan.patterns)
        try:
            if run.step == n * len(run.plan.angles):
                return self._finish(self._event(run.plan, "done"))
            i = run.step // n
            angle = run.plan.angles[i]
            if angle is not None and run.settled != i:
                run.angle = angle
                self.cmd_pub.publish(PolarizerCommand(target_deg=angle))
                self._wait("polarizer/state", self.params.settle_timeout_s)
                return self._check_settled()
            if self.stopping:
                raise ScanFault(f"stopped ({self.stop_reason})")
            self._trigger()
        except ScanFault as exc:
            self._fail(str(exc))

    def _check_settled(self) -> None:
        """The newest polarizer/state since the scan was asked for (each looked at once) against the
        commanded angle: settled there moves the scan on, a fault ends it."""
        run, seen = self.current, self._state
        if seen is None or seen[1] < run.requested_s:
            return
        self._state = None
        state, angle, tol = seen[0], run.angle, self.params.settle_tolerance_deg
        if state.fault:
            return self._fail(f"polarizer/state: fault at {state.angle_deg:g} deg: {state.fault}")
        if state.settled and abs(state.target_deg - angle) <= tol and abs(state.angle_deg - angle) <= tol:
            run.timing["analyzer_s"] += self.now() - run.since
            run.settled = run.step // len(run.plan.patterns)
            self._wait("")
            self._steps()

    def _trigger(self) -> None:
        """Light the step's pattern and have the grabber take it (the one blocking call, bounded)."""
        run = self.current
        plan, step = run.plan, run.step
        tag, where = plan.patterns[step % len(plan.patterns)], run.where()
        try:
            self.display.show(tag)
        except DriverError as exc:
            raise ScanFault(f"{where}: display: {exc}") from None
        self.pattern_pub.publish(Pattern.of(tag, plan.scan_id, step))
        t0 = self.now()
        try:
            ack = self.trigger.call(FrameRequest(scan_id=plan.scan_id, step=step, pattern=tag))
        except (BusError, TimeoutError) as exc:
            raise ScanFault(f"{where}: camera/trigger: {exc}") from None
        if not ack.ok:
            raise ScanFault(f"{where}: camera/trigger: {ack.detail}")
        run.timing["camera_s"] += self.now() - t0
        self._wait("camera/frame", self.params.frame_timeout_s)

    def _wait(self, what: str, timeout_s: float = math.inf) -> None:
        run = self.current
        run.waiting, run.since, run.deadline = what, self.now(), self.now() + timeout_s

    def _fail(self, text: str) -> None:
        run = self.current
        self.log.error("scan %d (%s) fault: %s", run.plan.scan_id, run.plan.method, text)
        self._finish(self._event(run.plan, "fault", text))

    def _finish(self, final: ScanEvent) -> None:
        """Blank the display, put the analyzer back, publish the scan's final event (done or fault)."""
        run, self.current = self.current, None
        try:
            self.display.blank()
        except DriverError as exc:
            self.log.error("display: %s", exc)
        if run.unpolarized and self.params.analyzer == "stage":
            try:
                self._mount(True)
            except ScanFault as exc:
                self.log.error("%s", exc)
        self.scan_pub.publish(final)
        if final.event == "done":
            t = run.timing
            self.log.info("scan %d (%s) done in %.3f s: %d frames, analyzer %.3f s, camera %.3f s, "
                          "frame wait %.3f s", run.plan.scan_id, run.plan.method, self.now() - run.started_s,
                          t["frames"], t["analyzer_s"], t["camera_s"], t["frame_wait_s"])

    def _mount(self, inserted: bool) -> None:
        try:
            ack = self.mount.call(AnalyzerMount(inserted=inserted))
        except (BusError, TimeoutError) as exc:
            raise ScanFault(f"camera/analyzer: {exc}") from None
        if not ack.ok:
            raise ScanFault(f"camera/analyzer: {ack.detail}")


NODE = Emitter
