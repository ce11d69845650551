"""The grabber node: takes one frame per ``camera/trigger`` and publishes it on ``camera/frame``.

The camera is a backend of :mod:`polarstripe.nodes.drivers` (``v4l2``, ``aravis``, ``file``, ``sim``, or one
added through the ``polarstripe.drivers`` entry points), named by ``camera`` and made from ``camera_options``
(the backend's own ``Options``: docs/nodes.md) when the node starts; ``exposure_s`` and ``gain`` are set
through the camera role. A trigger (:class:`~polarstripe.msgs.FrameRequest`: scan id, step, pattern tag) grabs
one :class:`~polarstripe.nodes.drivers.camera.CameraFrame` and publishes it as one ``Frame`` (the image as the
camera delivered it, with the exposure, gain and bit depth it was taken with) tagged with the pattern, the
scan and step, and the analyzer angle. The angle is decided here and only here, where the stage's state is
known: the newest ``polarizer/state`` when the frame is taken; None while the analyzer is out of the path (see
``camera/analyzer``), before any state came (no polarizer node), or for a polarization camera's frame: a
camera whose frame metadata names a 2×2 micro-polarizer mosaic (``mosaic_deg``, e.g. ``sim_polarization``)
has its frames published with those angles in ``Frame.mosaic_deg``. The reply is sent after the frame is
published, so a caller that then waits for the frame cannot miss it.

Faults are published, never painted over: a grab that times out, a camera that disappears or a frame of the
wrong scan is an ``Ack(ok=False, detail=…)`` reply naming the camera and what happened, an ERROR line on the
``log`` topic, and a count in the heartbeat (``grab_faults``); no frame is published for it. After a lost
camera the next trigger reopens it. A frame larger than ``$POLARSTRIPE_MAX_PIXELS``
(:func:`~polarstripe.runtime.params.check_frame_size`; a real camera set to a mode the rig cannot carry) is
dropped the same way, logged once and counted (``frames_oversize``); the node keeps running. A frame that
did not arrive whole (a GigE Vision packet lost: the backend raises ``FrameDropped``) is never published: a
fault reply, one ERROR line, counted in ``frames_dropped`` (and ``grab_faults``), and the camera stays open.

Services: ``camera/trigger`` (FrameRequest → Ack), ``camera/analyzer`` (:class:`AnalyzerMount` → Ack: put
the analyzer in or out of the optical path; in a lab rig a flip mount, in the simulator a flag per frame).
"""

from __future__ import annotations

import math
import time
from typing import Any

from polarstripe.msgs import Ack, AnalyzerMount, Frame, FrameRequest, PolarizerState
from polarstripe.nodes.drivers.backend import BackendContext
from polarstripe.nodes.drivers.errors import DriverError, FrameDropped
from polarstripe.nodes.drivers.registry import check_backend, open_backend
from polarstripe.runtime.bus import BusTimeout
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams, check_frame_size


class Grabber(Node):
    """Grabs a frame per trigger from a camera backend (see the module docstring)."""

    class Params(NodeParams):
        camera: str = "sim"  # backend: sim | sim_polarization | v4l2 | aravis | file, or an entry point's
        camera_options: dict[str, Any] = {}  # the backend's own options (its Options)
        exposure_s: float | None = None  # None: the backend's (the simulator's scene)
        gain: float | None = None  # None: the backend's
        grab_timeout_s: float = 10.0  # a grab (and a service the camera calls) that takes longer is a fault

        def validate(self):
            super().validate()
            check_backend("camera", self.camera, self.camera_options)
            if not self.grab_timeout_s > 0:
                raise ValueError(f"grab_timeout_s must be > 0, got {self.grab_timeout_s}")
            if self.exposure_s is not None and not (math.isfinite(self.exposure_s) and self.exposure_s > 0):
                raise ValueError(f"exposure_s must be a positive number of seconds, got {self.exposure_s}")

    PUBLISHES = {"camera/frame": Frame}
    SUBSCRIBES = {"polarizer/state": PolarizerState}
    SERVES = {"camera/trigger": (FrameRequest, Ack), "camera/analyzer": (AnalyzerMount, Ack)}

    def setup(self):
        self.frames = self.publisher("camera/frame")
        self.subscribe("polarizer/state", self.on_state, mode="latest")
        self.serve("camera/trigger", self.trigger)
        self.serve("camera/analyzer", self.set_analyzer)
        self.state: PolarizerState | None = None
        self.analyzer_in = True
        self.counters["grab_faults"] = 0
        self.counters["frames_oversize"] = 0  # frames beyond $POLARSTRIPE_MAX_PIXELS, dropped
        self.counters["frames_dropped"] = 0  # frames that did not arrive whole (lost packets): not published
        self.camera = None
        self._service_clients: dict = {}  # kept across reopening the camera
        try:
            self.camera = self.open_camera()
        except DriverError as exc:  # started without a camera: every trigger says so until one appears
            self.log.error("camera %r: %s", self.params.camera, exc)

    def teardown(self):
        if self.camera is not None:
            self.camera.close()
            self.camera = None

    # ---- camera --------------------------------------------------------------------------------------------
    def open_camera(self):
        """Open the backend named by ``camera`` with ``camera_options``, then set exposure and gain."""
        p = self.params
        context = BackendContext(service=self._service)
        cam = open_backend("camera", p.camera, p.camera_options, context=context)
        try:
            if p.exposure_s is not None:
                cam.exposure_s = p.exposure_s
            if p.gain is not None:
                cam.gain = p.gain
        except DriverError:
            cam.close()
            raise
        self.log.info("camera %s open", cam.name)
        return cam

    def _service(self, name: str, request_type: type, reply_type: type):
        """The call of service ``name`` for the camera (one client per service, bounded by
        ``grab_timeout_s``)."""
        if name not in self._service_clients:
            self._service_clients[name] = self.client(name, request_type, reply_type,
                                                      timeout_s=self.params.grab_timeout_s)
        return self._service_clients[name].call

    # ---- handlers ------------------------------------------------------------------------------------------
    def on_state(self, msg: PolarizerState) -> None:
        self.state = msg

    def set_analyzer(self, req: AnalyzerMount) -> Ack:
        self.analyzer_in = req.inserted
        return Ack(ok=True, detail="analyzer in" if req.inserted else "analyzer out")

    def _fault(self, req: FrameRequest, text: str) -> Ack:
        self.counters["grab_faults"] += 1
        self.log.error("frame of scan %d step %d (%s): %s", req.scan_id, req.step, req.pattern, text)
        return Ack(ok=False, detail=text)

    def analyzer_deg(self) -> float | None:
        """The frame's analyzer angle: None with the analyzer out of the path, else the newest
        ``polarizer/state`` (one that arrived since the loop last looked: the emitter saw it settle), None
        before any."""
        if not self.analyzer_in:
            return None
        try:
            self.state = self.wait_for("polarizer/state", timeout_s=0.0)
        except BusTimeout:
            pass
        return self.state.angle_deg if self.state is not None else None

    def trigger(self, req: FrameRequest) -> Ack:
        if self.camera is None:
            try:
                self.camera = self.open_camera()
            except DriverError as exc:
                return self._fault(req, f"camera {self.params.camera!r} unavailable: {exc}")
        cam = self.camera
        cam.request(req.pattern, analyzer=self.analyzer_in, scan_id=req.scan_id, step=req.step)
        if req.exposure_s is not None:
            try:
                cam.exposure_s = req.exposure_s
            except DriverError as exc:
                return self._fault(req, str(exc))
        t0 = time.monotonic()
        try:
            shot = cam.grab(timeout=self.params.grab_timeout_s + 1.0)
        except DriverError as exc:
            if isinstance(exc, FrameDropped):  # incomplete: nothing published, the camera stays open
                self.counters["frames_dropped"] += 1
            elif not isinstance(exc, TimeoutError):  # lost: reopen at the next trigger
                cam.close()
                self.camera = None
            return self._fault(req, f"{type(exc).__name__}: {exc}")
        h, w = shot.image.shape[:2]
        try:  # a camera that delivers more than the rig may carry (runtime/params.py): dropped, said once
            check_frame_size(w, h, what=f"camera {cam.name} frame")
        except ValueError as exc:
            self.counters["frames_oversize"] += 1
            if self.counters["frames_oversize"] == 1:
                self.log.error("%s; dropped (this and every such frame, counted as frames_oversize)", exc)
            self.counters["grab_faults"] += 1
            return Ack(ok=False, detail=str(exc))
        meta = shot.metadata
        if "scan_id" in meta and (meta["scan_id"], meta["step"]) != (req.scan_id, req.step):
            return self._fault(req, f"camera delivered scan {meta['scan_id']} step {meta['step']}")
        mosaic = [float(a) for a in meta.get("mosaic_deg", ())]  # a polarization camera's raw mosaic
        self.frames.publish(Frame(image=shot.image, exposure_s=shot.exposure_s, gain=shot.gain,
                                  bit_depth=shot.bit_depth, pattern=req.pattern,
                                  polarizer_deg=None if mosaic else self.analyzer_deg(), scan_id=req.scan_id,
                                  step=req.step, mosaic_deg=mosaic),
                            stamp_ns=shot.stamp_ns)
        return Ack(ok=True, detail=f"{w}x{h} in {time.monotonic() - t0:.3f} s")


NODE = Grabber
