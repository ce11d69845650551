"""The simulator node: projector, camera and polarizer stage of the default tank (or a scene file).

It serves frames rendered by the light-transport model (:mod:`polarstripe.sim.render`) for the pattern asked
for, at the analyzer angle of its simulated drive's *actual* position (or with no analyzer in the path),
through the EMVA 1288 sensor (:func:`polarstripe.sim.sensor.expose`); it publishes the ground truth the
compositor scores against at every scan start; it hosts a simulated
CiA 402 drive (:class:`~polarstripe.nodes.drivers.simdrive.SimCia402Drive`) on a python-can bus carried over
ZeroMQ, which the polarizer node drives with its real CANopen code (or, with ``ell14_link``, a simulated
Thorlabs ELL14 on a pty for the ``ell14`` backend); and it moves the virtual source when a plan arrives (the
in-situ loop of the paper's §4). ``medium_sigma_t``, ``medium_g``: a medium the other nodes do not know.
``velocity_m_s``, ``fps``: the rig moves during each scan, every frame rendered at the pose of its capture
time, the truth at the pose mid-scan (nodes/simulator_motion.py, docs/planning.md §11).

Services (relative to the namespace):

* ``simulator/render`` (:class:`RenderRequest` → :class:`~polarstripe.msgs.Frame`) — one frame; its
  ``polarizer_deg`` is the angle it was rendered at (the frame's analyzer angle on ``camera/frame`` is the
  grabber's, from ``polarizer/state``).
* ``simulator/render_mosaic`` (:class:`RenderRequest` → ``Frame``) — the raw frame of a polarization
  camera (the ``sim_polarization`` backend): each pixel through its own micro-polarizer of a 2×2 mosaic
  (sim/mosaic.py, the ``mosaic_*`` params), then the same sensor noise; ``mosaic_deg`` gives the layout.
* ``simulator/move_source`` (``Plan`` → ``Ack``) — move the source to ``plan.separation_m`` now; a
  ``planner/plan`` message moves it too, but only between scans (``emitter/scan`` start … done/fault).
* ``simulator/fault`` (:class:`SimFault` → ``Ack``) — inject a fault (see :data:`FAULT_COMMANDS`).
* ``simulator/target`` (``Empty`` → ``Ack``) — the ``target`` board (:class:`~.simulator_frames.Target`) to
  pose k mod N at the k-th call from 0 (it starts at pose 0); launch/calibrate.toml.

Topic ``simulator/truth`` (``Composite``, ``method`` "truth", ``scan_id`` the scan's), published at every
``emitter/scan`` start — the one way the ground truth reaches the compositor, so a recording carries it and a
replay scores like the live run: images ``S`` (float64: the unscattered object radiance under flood light,
:func:`polarstripe.sim.truth.unscattered_radiance`, docs/physics.md §10.8, in DN above the dark offset, no
analyzer, same exposure as the frames; the key keeps its name), ``depth_m`` (float32 z [m] of the objects, 0
where none), ``chart_band`` (int32 band per pixel, −1 off the chart), ``chart_high`` (bool, bright bar);
metrics ``separation_m``, ``exposure_s``, ``dark_offset_dn``, ``rig_geometry`` (camera and projector at the
current source pose, as a calibration file holds them: sim/depth_truth.py). One render per source pose,
cached.

Speed: frames are made on worker threads, ``threads`` at once (nodes/simulator_pipeline.py); the loop
never waits for one: a request whose frame is not made yet gets a deferred reply, which the ``deliver``
timer sends once it is, in request order. Each pattern's components are kept per source pose (their
analyzer basis, sim/polarization.py; the mosaic's Stokes only for ``render_mosaic``, whose first frame of
a pattern kept without them renders it again), so the second analyzer angle of a scan costs only the
analyzer pass and the sensor, and the scan's next ``threads`` × ``render_batch`` frames are made ahead
(``render_ahead``), each worker rendering a batch's patterns together (sim/scan_render.py). With
``render_scale`` > 1 (``preview`` picks it so the model runs at ~160 pixels wide) the model renders at a
lower resolution and the radiance is resized bilinearly to the camera's size before the sensor (noise,
quantisation and clipping at full size); checker patterns (whose edges the high-frequency separation relies
on) at twice that resolution, and the ground truth at full size.
``noise = "gaussian"`` (the preview default) draws shot and read noise as one normal variate with the EMVA
mean and variance instead of Poisson + normal.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time

from polarstripe.msgs import Ack, Composite, Empty, Frame, Plan, ScanEvent
from polarstripe.msgs.rig import RenderRequest, SimFault
from polarstripe.nodes.drivers.simdrive import SimCia402Drive
from polarstripe.nodes.simulator_frames import (
    PREVIEW_WIDTH,
    SimulatorError,
    Target,
    exposure_factor,
    host_ell14,
    micro_polarizers,
    model_scene,
    parse_fault,
    rig_scene,
    to_camera,
    truth_composite,
)
from polarstripe.nodes.simulator_motion import ScanMotion
from polarstripe.nodes.simulator_params import SimulatorParams
from polarstripe.nodes.simulator_pipeline import FrameDone, FrameJob, Frames, Owed, Sources
from polarstripe.runtime.liveness import RunState
from polarstripe.runtime.node import Node
from polarstripe.runtime.node_bus import Deferred
from polarstripe.sim.patterns import parse_pattern
from polarstripe.sim.render import resolve_fidelity
from polarstripe.sim.scene import Scene, SceneError, with_light, with_separation
from polarstripe.sim.sensor import electrons_per_radiance
from polarstripe.sim.threads import set_threads

__all__ = ["Simulator", "SimulatorError"]

DELIVER_PERIOD_S = 0.002  # how often the loop looks for made frames while one is owed


class Simulator(Node):
    """Stands in for projector, camera and polarizer stage (see the module docstring)."""

    Params = SimulatorParams

    PUBLISHES = {"simulator/truth": Composite}
    SUBSCRIBES = {"planner/plan": Plan, "emitter/scan": ScanEvent}
    SERVES = {
        "simulator/render": (RenderRequest, Frame),
        "simulator/render_mosaic": (RenderRequest, Frame),
        "simulator/move_source": (Plan, Ack),
        "simulator/fault": (SimFault, Ack),
        "simulator/target": (Empty, Ack),
    }

    def setup(self):
        p = self.params
        self.target = self.drive = self.ell14 = None  # teardown after a setup cut short
        self.frames = None
        try:
            self.base = rig_scene(p.scene, p.resolution, p.exposure_s, p.medium_sigma_t, p.medium_g)
            self.base = self.base if p.light == "scene" else with_light(self.base, p.light)
            self.fidelity = resolve_fidelity(p.fidelity)
            self.threads = set_threads(p.threads)
            self.target = Target.of(p, self.base, self.fidelity)
            self.base = self.base if self.target is None else self.target.place(self.base, 0)
        except SceneError as exc:
            raise SimulatorError(f"node {self.name!r}: {exc}") from None
        cam = self.base.camera
        self.scene = self.base
        w = cam.resolution[0]
        self.scale = p.render_scale or (
            max(1, w // PREVIEW_WIDTH) if self.fidelity.name == "preview" else 1)
        self.gaussian = p.noise == "gaussian" or (p.noise == "auto" and self.fidelity.name == "preview")
        if self.fidelity.name == "reference" and p.heartbeat_s > 0:  # its kernels hold the GIL up to ~1.1 s
            self.beat_period_s = max(p.heartbeat_s, 1.0)  # deadline 4 s (runtime/liveness.py)
        self.stats = {"frames": 0, "made_ahead": 0, "renders": 0, "cache_hits": 0, "model_s": 0.0,
                      "sensor_s": 0.0, "resize_s": 0.0, "busy_s": 0.0}
        self.sources = Sources(p.cache_size, self.fidelity)
        self.frames = Frames(self.sources, self.threads, self.stats, p.render_batch)
        self.motion = ScanMotion(p)
        self._truth: dict = {}
        self._e_map_base = electrons_per_radiance(cam)
        self._e_map = self._e_map_base
        self.camera_lost, self.frame_delay_s = False, 0.0
        if p.can_channel:  # kept before it starts: a stop signal mid-start leaves teardown a drive to stop
            self.drive = SimCia402Drive(p.can_channel, p.can_node_id, speed_counts_s=p.drive_speed_counts_s,
                                        settle_s=p.drive_settle_s)
            self.drive.start()
        if p.ell14_link:
            self.ell14 = host_ell14(p.ell14_link, self.name, self.log)
        for command in p.faults:
            self.inject(SimFault(command=command), strict=True)
        self.run_state = RunState.of(self.graph, self.name)  # the source pose outlives a respawn
        if "separation_m" in self.run_state:
            self.scene = with_separation(self.base, float(self.run_state.get("separation_m")))
            self.log.info("source restored to d_LC = %.3f m (run state)", self.scene.separation_m())
        self._expose_for_flood()
        self.scanning: set[int] = set()  # scans started and not yet ended (emitter/scan)
        self.pending_plan: Plan | None = None
        self.truth_pub = self.publisher("simulator/truth")
        self.subscribe("planner/plan", self.on_plan, mode="latest")
        self.subscribe("emitter/scan", self.on_scan, mode="all")
        self.serve("simulator/render", self.render)
        self.serve("simulator/render_mosaic", self.render_mosaic)
        self.mosaic = micro_polarizers(p)
        self.serve("simulator/move_source", self.move_source)
        self.serve("simulator/fault", self.inject)
        self.serve("simulator/target", self.move_target)
        self.log.info("%dx%d camera, fidelity %s, model at 1/%d, %d frames at once, %s noise, drive %s", w,
                      cam.resolution[1], self.fidelity.name, self.scale, self.threads,
                      "gaussian" if self.gaussian else "poisson", p.can_channel or "none (fixed analyzer)")

    def teardown(self):
        if self.target is not None:
            self.target.close()
        if self.ell14 is not None:
            self.ell14.stop()
            if os.path.islink(self.params.ell14_link):
                os.unlink(self.params.ell14_link)
            self.ell14 = None
        for owed in self.frames.close() if self.frames is not None else []:
            owed.reply.fail(SimulatorError(f"node {self.name!r} stopped before the frame was made"))
        if self.drive is not None:
            self.drive.stop()
            self.drive = None
        self.log.info("stats %s", json.dumps({k: round(v, 4) for k, v in self.stats.items()}))

    # ---- state ---------------------------------------------------------------------------------------------
    def analyzer_angle(self) -> float:
        """The analyzer angle [deg]: the simulated CiA 402 drive's actual position, else the simulated
        ELL14's, else the ``analyzer_deg`` param."""
        if self.drive is not None:
            return float(self.drive.axis.position) / self.params.counts_per_deg  # counts, the model's own
        if self.ell14 is not None:
            return self.ell14.position * 360.0 / self.ell14.pulses_per_rev
        return self.params.analyzer_deg

    def _pose(self, scene: Scene | None = None) -> tuple:
        scene = self.scene if scene is None else scene
        return (scene.camera.position, scene.projector.position, scene.projector.look_at,
                None if self.target is None else self.target.index)

    def _truth_key(self) -> tuple:
        return (*self._pose(), self.scene.camera.exposure_s)

    def _where(self, pattern: str, scan_id: int = 0, step: int = 0) -> tuple[tuple, Scene]:
        """(pose, model scene) of frame ``step`` of scan ``scan_id`` showing ``pattern``: the current scene,
        or where a moving rig is then (nodes/simulator_motion.py)."""
        scene = self.motion.scene_at(self.scene, scan_id, step)
        return self._pose(scene), model_scene(scene, pattern, self.scale, self.target is not None)

    def move_to(self, separation_m: float) -> Scene:
        """Move the source to camera–source distance ``separation_m`` [m] (the projector keeps its aim)."""
        if not (math.isfinite(separation_m) and separation_m > 0):
            raise SimulatorError(f"plan: separation_m={separation_m} must be a positive number of metres")
        self.scene = with_separation(self.base, separation_m)
        self._expose_for_flood()
        self.run_state.save(separation_m=separation_m)  # restored by a respawned simulator
        return self.scene

    def _expose_for_flood(self) -> None:
        """Auto exposure (``auto_exposure``): the base exposure, shortened so that the 99.5th percentile of
        the flood frame without analyzer stays at 85 % of the sensor's range (ADC or full well, above the dark
        offset). The same exposure then serves every method and the ground truth."""
        base = self.base.camera
        factor = 1.0
        if self.params.auto_exposure:
            source, seconds = self.sources.get(("flood", self._pose()), self._where("flood")[1], "flood")
            self.frames.count(FrameDone(None, seconds, 0.0, 0.0))
            radiance = to_camera(source.total(), base.resolution)
            factor = exposure_factor(radiance, self._e_map_base, base)
        self.scene = self.scene.replace(camera=base.replace(exposure_s=base.exposure_s * factor))
        self._e_map = self._e_map_base * factor
        if factor < 1.0:
            self.log.info("auto exposure: %.3g s (flood would clip at %.3g s)", self.scene.camera.exposure_s,
                          base.exposure_s)

    # ---- handlers ------------------------------------------------------------------------------------------
    def on_scan(self, event: ScanEvent) -> None:
        if event.event == "start":
            self.scanning.add(event.scan_id)
            self.motion.start(event)  # moving, the rig passes this pose mid-scan (nodes/simulator_motion.py)
            # the pose cannot change until the scan ends: this is the truth of every frame of the scan
            self.truth_pub.publish(dataclasses.replace(self.truth(), scan_id=event.scan_id))
            return
        self.scanning.discard(event.scan_id)
        self.motion.end(event.scan_id)
        if not self.scanning and self.pending_plan is not None:
            plan, self.pending_plan = self.pending_plan, None
            self.on_plan(plan)

    def on_plan(self, plan: Plan) -> None:
        """A plan on ``planner/plan`` moves the source — after the scan that is running, never during one."""
        if self.scanning:
            self.pending_plan = plan
            return
        if abs(self.scene.separation_m() - plan.separation_m) < 1e-9:
            return
        try:
            self.move_to(plan.separation_m)
            self.log.info("plan: source moved to d_LC = %.3f m", plan.separation_m)
        except SimulatorError as exc:
            self.log.error("%s", exc)

    def move_target(self, _req: Empty) -> Ack:
        """``simulator/target``: the board to its next pose (the k-th call: pose k mod N), re-exposed."""
        if self.target is None:
            return Ack(ok=False, detail="simulator/target: no target (param 'target')")
        self.base = self.target.place(self.base, self.target.advance())
        self.scene = self.scene.replace(objects=self.base.objects, projector=self.scene.projector.replace(
            intensity_w_sr=self.base.projector.intensity_w_sr))     # the pose's light (Target)
        self._expose_for_flood()
        self.log.info("%s", self.target.describe())
        return Ack(ok=True, detail=self.target.describe())

    def move_source(self, plan: Plan) -> Ack:
        try:
            self.move_to(plan.separation_m)
        except SimulatorError as exc:
            return Ack(ok=False, detail=str(exc))
        pos = ", ".join(f"{v:.3f}" for v in self.scene.projector.position)
        self.log.info("source moved to d_LC = %.3f m (projector at %s)", plan.separation_m, pos)
        return Ack(ok=True, detail=f"separation_m={plan.separation_m:.6g} projector=({pos})")

    def render(self, req: RenderRequest) -> Frame:
        """``simulator/render``: a frame through the analyzer at the drive's angle, or without one."""
        return self._frame(req, mosaic=False)

    def render_mosaic(self, req: RenderRequest) -> Frame:
        """``simulator/render_mosaic``: the raw frame of a polarization camera, each pixel through its own
        micro-polarizer (sim/mosaic.py, the ``mosaic_*`` params); ``mosaic_deg`` gives the layout."""
        return self._frame(req, mosaic=True)

    def _frame(self, req: RenderRequest, *, mosaic: bool) -> Frame | Deferred:
        """A frame request: its job made on a worker (or taken from the frames made ahead), the scan's next
        frames started, the reply at once if the frame is there, else deferred (:meth:`_deliver`)."""
        t_start = time.perf_counter()
        if self.camera_lost:
            raise SimulatorError("simulated camera lost (fault 'camera_lost on')")
        cam = self.scene.camera
        e_map = self._e_map
        if req.exposure_s is not None:
            if not (math.isfinite(req.exposure_s) and req.exposure_s > 0):
                raise SimulatorError(f"exposure_s={req.exposure_s} must be a positive number of seconds")
            cam = cam.replace(exposure_s=req.exposure_s)
            if cam.exposure_s != self.scene.camera.exposure_s:
                e_map = self._e_map * cam.exposure_s / self.scene.camera.exposure_s
        pattern = req.pattern.strip().lower()
        if pattern != "off":
            try:
                parse_pattern(pattern)
            except SceneError as exc:
                raise SimulatorError(f"pattern {req.pattern!r}: {exc}") from None
        seed = self.params.seed if self.params.seed is not None else cam.seed
        pose, model = self._where(pattern, req.scan_id, req.step)
        job = FrameJob(pattern, pose, None if pattern == "off" else model,
                       self.analyzer_angle() if req.analyzer and not mosaic else None,
                       self.mosaic if mosaic else None, cam, e_map,
                       (seed, req.scan_id, req.step, self.stats["frames"]), self.gaussian)
        self.stats["frames"] += 1
        future = self.frames.start(job, self._where if self.params.render_ahead else None)
        owed = Owed(req, job, future, t_start, mosaic, self.now() + self.frame_delay_s)
        if not self.frames.owed and future.done() and self.frame_delay_s <= 0:
            return self._answer(owed)
        owed.reply = Deferred()
        self.frames.owed.append(owed)
        if len(self.frames.owed) == 1:
            self.every(DELIVER_PERIOD_S, self._deliver, name="deliver")
        return owed.reply

    def _deliver(self) -> None:
        """The ``deliver`` timer: answer the owed frames that are made (and delayed as long as the fault
        ``frame_delay`` asks), in request order."""
        while (owed := self.frames.ready(self.now())) is not None:
            try:
                owed.reply.reply(self._answer(owed))
            except Exception as exc:  # noqa: BLE001 - the caller gets it, as from a handler
                owed.reply.fail(exc)
        if not self.frames.owed:
            self.cancel("deliver")

    def _answer(self, owed: Owed) -> Frame:
        try:
            done = owed.future.result()
        except SceneError as exc:
            raise SimulatorError(f"pattern {owed.req.pattern!r}: {exc}") from None
        self.frames.count(done)
        t_end = time.perf_counter()
        self.stats["busy_s"] += t_end - owed.t_start
        req, job = owed.req, owed.job
        self.log.debug("frame scan %d step %d %s: %.4f s (sensor %.4f s)", req.scan_id, req.step, job.pattern,
                       t_end - owed.t_start, done.sensor_s)
        return Frame(image=done.image, exposure_s=job.camera.exposure_s, bit_depth=job.camera.bits,
                     pattern=job.pattern, polarizer_deg=job.angle, scan_id=req.scan_id, step=req.step,
                     mosaic_deg=list(self.mosaic.layout) if owed.mosaic else [])

    def truth(self) -> Composite:
        """The ground truth at the current source pose and exposure (cached; ``scan_id`` 0)."""
        key = self._truth_key()
        if key not in self._truth:
            self._truth[key] = truth_composite(self.scene)
        return self._truth[key]

    def inject(self, req: SimFault, strict: bool = False) -> Ack:
        try:
            name, args = parse_fault(req.command)
            if name == "camera_lost":
                self.camera_lost = (args or ["on"])[0] == "on"
            elif name == "frame_delay":
                self.frame_delay_s = float(args[0])
            else:
                if self.drive is None:
                    raise ValueError(f"fault {name!r} needs the simulated drive (param can_channel)")
                d = self.drive
                {"never_settle": lambda: d.inject_never_settle((args or ["on"])[0] == "on"),
                 "emcy": lambda: d.inject_emcy(int(args[0], 0) if args else 0x8611),
                 "heartbeat_stop": lambda: d.inject_heartbeat_stop(float(args[0]) if args else None),
                 "heartbeat_resume": d.resume_heartbeat,
                 "bus_off": lambda: d.inject_bus_off(float(args[0])),
                 "position_limit": lambda: d.inject_position_limit(int(args[0]), int(args[1])),
                 }[name]()
        except (ValueError, IndexError) as exc:
            if strict:
                raise SimulatorError(f"node {self.name!r}: param 'faults': {exc}") from None
            return Ack(ok=False, detail=f"fault {req.command!r}: {exc}")
        self.log.warning("fault injected: %s", req.command)
        return Ack(ok=True, detail=req.command)


NODE = Simulator
