"""The sequencer node: runs the demo of ``launch/sim.toml`` from start to end, then exits.

0. Wait until every other node of the launch graph has been heard on ``heartbeat`` and says it is ready (no
   ``starting`` in its counters: its setup is done). Start-up is tied to readiness: a node not heard at all
   within ``startup_timeout_s``, or heard starting and then silent, is a clear fault; one that keeps beating
   while it sets up (the planner plans) is waited for up to ``setup_timeout_s``.
1. Optionally ask the planner for a plan (``planner/plan``, Empty → Plan) and have the simulator move its
   source there (``simulator/move_source``, Plan → Ack; its reply comes after the move); optionally measure
   E_b, the analyzer angle of least backscatter (``polarizer/calibrate``), else take the ``eb_deg`` param.
2. Before polarized scans, wait until ``polarizer/state`` shows no fault (the stage may still be connecting);
   with ``analyzer = "mosaic"`` (a polarization camera) there is no stage: no wait, no calibration, and
   polarized scans ask for no angles.
   For each method of the ``methods`` param: call ``emitter/start_scan``, wait for that scan's ``done`` or
   ``fault`` on ``emitter/scan`` and, if ``wait_composite``, for the compositor's ``compositor/composite`` of
   that scan.
3. Every wait of a scan depends on the nodes it needs (``scan_peers``, and ``polarized_peers`` for a polarized
   method, those of the launch graph): one that stops beating on ``heartbeat`` (runtime/liveness.py: 4 missed
   periods, 1 s by default), exits or is respawned ends the wait at once with a line naming it. If the launch
   respawns it, the sequencer waits (``respawn_wait_s``) until it beats again with a new incarnation and the
   interrupted scan has ended, then retries the scan once and says so; otherwise the sequence ends there.
4. With an ``estimator`` node in the launch graph (``rescan``; nodes/sequencer_rescan.py): after a pass over
   the methods, wait for its ``medium/estimate`` of one of the pass's scans and the plan the planner publishes
   in answer to it (``curves["estimate_scan_id"]``); when that plan's separation is more than one step of its
   grid away from the one scanned and its curve predicts a gain there (``min_gain``), move the source there
   and scan the methods again (``max_rescans``), saying so.
5. Stop with exit status 0 when every scan was done (and composited without a ``metrics["error"]``), 1
   otherwise — so ``polarstripe launch launch/sim.toml --once`` ends (the sequencer is its ``required`` node).

Services that are not up yet, or whose node is lost and respawned, are retried until ``startup_timeout_s``
(runtime/client.py); every wait has a timeout, and the text of a failure names the service or topic and what
happened.
"""

from __future__ import annotations

import time
from typing import Literal

from polarstripe.msgs import (
    METHOD_NAMES,
    Ack,
    CalibrateRequest,
    Calibration,
    Composite,
    Empty,
    Heartbeat,
    MediumEstimate,
    Method,
    Plan,
    PolarizerState,
    ScanEvent,
    ScanRequest,
)
from polarstripe.nodes.sequencer_report import scores, summary
from polarstripe.nodes.sequencer_rescan import Rescanning
from polarstripe.runtime.bus import RECONNECT_MAX_S, BusError, BusTimeout
from polarstripe.runtime.liveness import STARTING_DEADLINE_S, PeerLost
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams


class Sequencer(Rescanning, Node):
    """Runs a fixed list of scans once (see the module docstring)."""

    class Params(NodeParams):
        methods: list[str] = list(METHOD_NAMES)
        stripes: int = 30
        sheets: int = 0  # sheets per stripe frame; 0: the plan's (plan = true), else the emitter's param
        eb_deg: float = 0.0  # analyzer angle of least backscatter E_b [deg]; E_w = E_b + 90
        calibrate: bool = False  # measure E_b first with polarizer/calibrate (overrides eb_deg)
        plan: bool = True  # ask planner/plan first
        move_source: bool = True  # have the simulator move its source to the plan
        wait_composite: bool = True  # wait for compositor/composite after each scan
        startup_timeout_s: float = 30.0  # nodes and services may take this long to come up (first heartbeat)
        setup_timeout_s: float = 600.0  # a node heard "starting" (its setup) may take this long to be ready
        ready_margin_s: float = 0.3  # after every node was heard, for subscriptions to settle
        scan_timeout_s: float = 600.0
        composite_timeout_s: float = 60.0
        scan_peers: list[str] = ["emitter", "grabber", "simulator", "compositor"]  # a scan's waits need them
        polarized_peers: list[str] = ["polarizer"]  # … and a polarized scan's these
        respawn_wait_s: float = 60.0  # a lost node the launch respawns: its return and the old scan's end
        rejoin_s: float = RECONNECT_MAX_S + 0.2  # … then this long, so its subscribers have reconnected
        repeat: int = 1  # passes over methods; 0: scan until stopped (polarstripe bench soak)
        rescan: bool = True  # rescan when an estimate moves the plan by more than one grid step (step 4)
        max_rescans: int = 1
        min_gain: float = 0.01  # … and the new plan predicts its objective this much higher there (step 4)
        estimator: str = "estimator"  # the node whose medium/estimate a pass waits for, if in the graph
        estimate_timeout_s: float = 300.0  # for the estimate and the plan answering it (fit + re-plan)
        analyzer: Literal["stage", "mosaic"] = "stage"  # mosaic: a polarization camera (no stage to wait for,
        # calibrate or turn; polarized scans ask for no angles)

        def validate(self):
            super().validate()
            if not self.methods:
                raise ValueError("methods must name at least one scan method")
            for method in self.methods:
                Method.parse(method)
            if self.stripes < 1:
                raise ValueError(f"stripes must be >= 1, got {self.stripes}")
            if not 0 <= self.sheets <= self.stripes:
                raise ValueError(f"sheets must be 0..stripes ({self.stripes}), got {self.sheets}")
            if self.max_rescans < 0:
                raise ValueError(f"max_rescans must be >= 0, got {self.max_rescans}")
            if self.repeat < 0:
                raise ValueError(f"repeat must be >= 0 (0: until stopped), got {self.repeat}")

    SUBSCRIBES = {
        "heartbeat": Heartbeat,
        "emitter/scan": ScanEvent,
        "compositor/composite": Composite,
        "polarizer/state": PolarizerState,
        "medium/estimate": MediumEstimate,
        "planner/plan": Plan,
    }

    def setup(self):
        self.subscribe("emitter/scan", mode="all")
        self.subscribe("compositor/composite", mode="all")
        self.subscribe("polarizer/state", mode="latest")
        self.subscribe("heartbeat", mode="all")
        self.subscribe("medium/estimate", mode="all")
        self.subscribe("planner/plan", mode="all")
        self.plan: Plan | None = None
        self.pass_scans: list[int] = []
        self.watch("heartbeat")  # runtime/liveness.py: waits on a lost peer end at once
        self.results: dict[str, dict] = {}

    def run(self) -> None:
        try:
            ok = self.sequence()
        except (SequenceError, PeerLost) as exc:  # PeerLost: a call's server lost outside a scan
            self.log.error("%s", exc)
            ok = False
        if self.results:
            self.log.info("results:\n%s", summary(self.results))
        if not self.stopping:
            self.stop("sequence finished" if ok else "sequence failed", exit_code=0 if ok else 1)
        for _ in self.events():  # ends with Stop
            pass

    # ---- steps ---------------------------------------------------------------------------------------------
    def call(self, service: str, req_type, resp_type, request, *, timeout_s: float = 2.0):
        """Call ``service``, retried while it is not up (or its node is respawned) until
        ``startup_timeout_s`` (runtime/client.py). A server lost for good raises ServiceLost, a PeerLost:
        a scan's recovery takes it (:meth:`scan`)."""
        client = self.client(service, req_type, resp_type, timeout_s=timeout_s)
        try:
            return client.call(request, retry_s=self.params.startup_timeout_s)
        except PeerLost:
            raise
        except BusError as exc:
            raise SequenceError(f"{service}: {exc}") from None

    def move_source_to(self, plan: Plan) -> None:
        """Have the simulator move its source to ``plan`` (``simulator/move_source``: it replies after the
        move)."""
        ack = self.call("simulator/move_source", Plan, Ack, plan, timeout_s=30.0)
        if not ack.ok:
            raise SequenceError(f"simulator/move_source: {ack.detail}")

    def wait_graph_ready(self) -> None:
        """Wait until every other node of the launch graph has been heard (its heartbeat), then one more beat
        period: a message published before a subscriber has connected is lost (ZeroMQ's slow joiner), and the
        first scan start makes the simulator publish its ground truth, which the compositor and the recorder
        must both see. Without a graph (a node run by itself) there is nothing to wait for."""
        expected = set(self.graph.get("nodes", {})) - {self.name}
        p, t0 = self.params, self.now()
        last: dict[str, float] = {}  # when each node was last heard
        ready: set[str] = set()  # nodes whose setup is done (a beat without "starting")
        while expected and not expected <= ready and not self.stopping:
            for hb in self.take("heartbeat", 0.1):
                if hb.node in expected:
                    last[hb.node] = self.now()
                    if not hb.counters.get("starting"):
                        ready.add(hb.node)
            now, unheard = self.now(), expected - set(last)
            if unheard and now - t0 > p.startup_timeout_s:
                raise SequenceError(f"heartbeat: {', '.join(sorted(unheard))} not heard within "
                                    f"{p.startup_timeout_s:g} s")
            for name in sorted(set(last) - ready):
                if now - last[name] > STARTING_DEADLINE_S:
                    raise SequenceError(f"node {name!r} lost during its start-up: no heartbeat for "
                                        f"{now - last[name]:.1f} s")
                if now - t0 > p.setup_timeout_s:
                    raise SequenceError(f"node {name!r} still starting after {p.setup_timeout_s:g} s")
        if expected:
            settle = self.now() + self.params.ready_margin_s
            while self.now() < settle and not self.stopping:
                self.take("heartbeat", settle - self.now())

    def sequence(self) -> bool:
        p = self.params
        self.wait_graph_ready()
        if p.plan:
            plan = self.plan = self.call("planner/plan", Empty, Plan, Empty(), timeout_s=30.0)
            self.log.info("plan: %s, d_LC = %.3f m, scan %s", plan.modality, plan.separation_m,
                          plan.scan_type or "-")
            if p.move_source:
                self.move_source_to(plan)
        self.eb_deg = p.eb_deg
        stage = p.analyzer == "stage"
        if stage and (p.calibrate or any(Method(m).polarized for m in p.methods)):
            self.wait_stage_ready()
        if p.calibrate and stage:

            cal = self.call("polarizer/calibrate", CalibrateRequest, Calibration, CalibrateRequest(),
                            timeout_s=60.0)
            if not cal.ok or cal.angle_deg is None:
                raise SequenceError(f"polarizer/calibrate: {cal.detail}")
            self.eb_deg = cal.angle_deg
            self.log.info("calibrated: E_b = %.2f deg", self.eb_deg)
        ok, passes, rescans = True, 0, 0
        while p.repeat == 0 or passes < p.repeat + rescans:
            self.pass_scans = []
            for method in p.methods:
                if self.stopping:
                    return False
                ok &= self.scan(method)
            passes += 1
            if rescans < p.max_rescans and self.plan_moved():
                rescans += 1
        return ok

    def wait_stage_ready(self) -> None:
        """Wait until the polarizer reports a state without a fault (it may still be connecting)."""
        last: list[PolarizerState] = []

        def ready(s: PolarizerState) -> bool:
            last[:] = [s]
            return not s.fault

        try:
            self.wait_for("polarizer/state", ready, self.params.startup_timeout_s)
        except BusTimeout:
            why = f"last fault: {last[0].fault}" if last else "no state at all"
            raise SequenceError(f"polarizer/state: the analyzer stage was not ready within "
                                f"{self.params.startup_timeout_s:g} s ({why})") from None

    def scan_peers(self, method: str) -> list[str]:
        """The nodes of the launch graph that the waits of a ``method`` scan depend on."""
        p, nodes = self.params, self.graph.get("nodes", {})
        polarized = Method(method).polarized and p.analyzer == "stage"
        names = [*p.scan_peers, *(p.polarized_peers if polarized else [])]
        return [n for n in names if n in nodes and n != self.name
                and (p.wait_composite or n != "compositor")]

    def scan(self, method: str) -> bool:
        """One scan of ``method``; a node lost meanwhile and respawned by the launch: the scan once more."""
        self.sid, self.scan_ended = 0, False
        try:
            return self.scan_once(method)
        except PeerLost as exc:
            lost = exc
        self.log.error("%s: scan %d: %s", method, self.sid, lost)
        self.results[method] = {"event": "peer_lost", "detail": str(lost)}
        try:
            self.recover(lost, self.sid)
            self.log.warning("%s: retrying the scan once: node %r is back (incarnation %d)", method,
                             lost.node, self.liveness.peers[lost.node].incarnation)
            return self.scan_once(method)
        except PeerLost as again:
            self.results[method] = {"event": "peer_lost", "detail": str(again)}
            raise SequenceError(f"{method}: scan {self.sid} (retried for {lost.node!r}): {again}") from None

    def recover(self, lost: PeerLost, sid: int) -> None:
        """Wait until ``lost.node`` beats again as a new incarnation and the emitter has ended scan ``sid``
        (a fault when a peer died under it), both within ``respawn_wait_s``; SequenceError otherwise."""
        node = self.graph.get("nodes", {}).get(lost.node, {})
        if not node.get("respawn"):
            raise SequenceError(f"node {lost.node!r} lost and the launch does not respawn it: stopping")
        deadline = self.now() + self.params.respawn_wait_s
        while not self.liveness.back(lost.node, lost.incarnation):
            if self.now() >= deadline or self.stopping:
                raise SequenceError(f"node {lost.node!r} lost and not back within "
                                    f"{self.params.respawn_wait_s:g} s")
            self.take("heartbeat", 0.05)
        self.liveness.forgive(lost.node)
        # the new process is heard by each subscriber only once its socket has reconnected, up to
        # RECONNECT_MAX_S after the bind (runtime/bus.py): a retry's start sent sooner can miss the compositor
        settled = self.now() + self.params.rejoin_s
        while self.now() < settled and not self.stopping:
            self.take("heartbeat", min(0.05, max(0.0, settled - self.now())))
        if lost.node != "emitter" and sid and not self.scan_ended:  # it must end before the retry starts
            try:
                self.wait_for("emitter/scan", lambda e: e.scan_id == sid and e.event in ("done", "fault"),
                              max(0.0, deadline - self.now()), peers=["emitter"])
            except BusTimeout:
                self.log.warning("scan %d: the emitter has not ended it within %g s", sid,
                                 self.params.respawn_wait_s)

    def peer_behind_fault(self, peers: list[str]) -> None:
        """After a scan's fault: raise PeerLost if one of ``peers`` died under it. A fault can come before
        the dead peer's deadline (the polarizer sees the simulator's drive go silent after 0.5 s), so wait
        until each peer has beaten since the fault or is lost (at most the deadline, 1 s by default)."""
        since, live = self.now(), self.liveness
        while not self.stopping:
            self.check_peers(peers)
            if all(live.peers[n].last_s > since for n in peers if n in live.peers):
                return
            self.take("heartbeat", 0.05)

    def scan_once(self, method: str) -> bool:
        p = self.params
        peers = self.scan_peers(method)
        polarized = Method(method).polarized and p.analyzer == "stage"
        sheets = (p.sheets or (self.plan.sheets if self.plan is not None else 0)) if Method(method).striped \
            else 0
        req = ScanRequest(method=method, stripes=p.stripes if Method(method).striped else 0,
                          analyzer_deg=[self.eb_deg, self.eb_deg + 90.0] if polarized else [], sheets=sheets)
        t0 = time.monotonic()
        reply = self.call("emitter/start_scan", ScanRequest, ScanEvent, req, timeout_s=5.0)
        if reply.event == "fault":
            self.log.error("%s: emitter refused: %s", method, reply.detail)
            self.results[method] = {"event": "fault", "detail": reply.detail}
            return False
        sid = self.sid = reply.scan_id
        self.pass_scans.append(sid)
        self.scan_ended = False
        try:
            end = self.wait_for("emitter/scan", lambda e: e.scan_id == sid and e.event in ("done", "fault"),
                                p.scan_timeout_s, peers=peers)
        except BusTimeout:
            self.log.error("%s: scan %d: no done/fault on emitter/scan within %g s", method, sid,
                           p.scan_timeout_s)
            self.results[method] = {"event": "timeout"}
            return False
        scan_s = time.monotonic() - t0
        self.results[method] = {"event": end.event, "detail": end.detail, "scan_s": scan_s}
        self.scan_ended = True
        if end.event == "fault":
            self.log.error("%s: scan %d fault: %s", method, sid, end.detail)
            self.peer_behind_fault(peers)  # a peer that died under the scan: PeerLost, the retry path
            return False
        self.log.info("%s: scan %d done in %.2f s", method, sid, scan_s)
        if not p.wait_composite:
            return True
        try:
            comp = self.wait_for("compositor/composite", lambda c: c.scan_id == sid, p.composite_timeout_s,
                                 peers=peers)
        except BusTimeout:
            self.log.error("%s: scan %d: no compositor/composite within %g s", method, sid,
                           p.composite_timeout_s)
            return False
        shown = {k: v for k, v in comp.metrics.items() if isinstance(v, (int, float, str))}
        depth = comp.metrics.get("depth")
        if isinstance(depth, dict):   # a stripe scan's depth: its valid fraction (of the objects' pixels when
            # the truth says which they are) and RMS, or why none
            valid = depth.get("valid_fraction_of_objects", depth.get("valid_fraction"))
            shown.update({"depth_valid_fraction": valid, "depth_rms_mm": depth.get("depth_rms_mm"),
                          "depth_error": depth.get("error")})
        self.results[method]["metrics"] = shown
        if comp.metrics.get("error"):  # nothing to composite: the scan produced no image
            self.log.error("%s: scan %d: compositor/composite error: %s", method, sid, comp.metrics["error"])
            self.results[method]["event"] = "composite_error"
            return False
        self.log.info("%s: %s", method, scores(shown))
        return True


class SequenceError(Exception):
    """A step of the sequence failed; the text names the service and what happened."""


NODE = Sequencer
