"""The simulator's frames, made on worker threads (the model's frame pool, sim/threads.py ``submit_frame``:
``threads`` frames at once, one model thread each) while the node's loop goes on.

A frame request becomes a :class:`FrameJob` that holds everything its frame depends on: the pattern, the
source pose, the model's scene, the analyzer angle read at the request, the camera and its exposure, the
electrons map, the noise seed (the node's seed, scan id, step and frame number). :func:`make_frame` makes
it: the pattern's :class:`FrameSource` (rendered once per pattern and pose, :class:`Sources`), the analyzer
(sim/polarization.py ``through_analyzer``), the resize to the camera, the sensor. The same job gives the
same frame on any thread.

**Ahead.** :func:`next_jobs` predicts the scan's next frames: the pattern that follows
(msgs/patterns.py ``following``), the next step and frame number, the same angle, exposure and pose. The
node starts them at once, so that while one frame travels the next ones render on the other cores; a
request whose job equals a predicted one takes that frame, which is the frame it would have got. A
prediction that does not come true (the analyzer moved, the scan ended) is cancelled or dropped.

**Together.** The frames made ahead go to the workers in batches of ``batch``: one worker renders the
sources a batch lacks side by side (sim/scan_render.py ``render_scan``: the grid solves of the batch as
one, the same components to the bit), then makes its frames in order, each Future set as its frame is
made. :class:`Frames` keeps ``threads × batch`` frames ahead and starts a batch once that many are
missing (fewer at a scan's end, or when the workers would run dry), so both cores render while the
frames travel. A batch holds only frames of one model scene (one pose, one resolution).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import OrderedDict, deque
from concurrent.futures import Future

import numpy as np
from polarstripe.heap import shared_zeros
from polarstripe.msgs.patterns import following
from polarstripe.msgs.rig import RenderRequest
from polarstripe.nodes.simulator_frames import to_camera
from polarstripe.sim.mosaic import MicroPolarizerArray, mosaic_radiance
from polarstripe.sim.polarization import AnalyzerBasis, analyzer_basis, through_analyzer
from polarstripe.sim.render import render_components
from polarstripe.sim.scan_render import render_scan
from polarstripe.sim.scene import Camera, Scene
from polarstripe.sim.sensor import expose
from polarstripe.sim.threads import submit_frame


@dataclasses.dataclass(frozen=True)
class FrameSource:
    """What the frames of one pattern need of its components: the analyzer's angle-free part (``basis``:
    D + A + B and the polarized light) and the linear Stokes (S1, S2) = (Bq + Sq, Bu + Su) for the mosaic
    (None when made for analyzer frames only: two fewer frames of memory kept per pattern), at the model's
    resolution."""

    basis: AnalyzerBasis
    s1: np.ndarray | None
    s2: np.ndarray | None

    def total(self) -> np.ndarray:
        """D + A + B, the radiance without analyzer."""
        return self.basis.total.reshape(self.basis.shape)


def frame_source(scene: Scene, pattern: str, fidelity, stokes: bool = True) -> FrameSource:
    """The :class:`FrameSource` of ``pattern``, with (S1, S2) if ``stokes``."""
    return _source(render_components(scene, pattern, fidelity), stokes)


def _source(comp, stokes: bool) -> FrameSource:
    if not stokes:
        return FrameSource(analyzer_basis(comp), None, None)
    return FrameSource(analyzer_basis(comp), _stokes(comp.Bq, comp.Sq), _stokes(comp.Bu, comp.Su))


def _stokes(b: np.ndarray, s: np.ndarray) -> np.ndarray:
    """b + s: the backscatter's and the object light's Stokes; ``b`` itself where ``s`` is the shared zeros
    (no port) and ``b`` holds its own memory (a kept source then pins no other array of the model's)."""
    owner = b if b.base is None else b.base
    if s is shared_zeros(b.shape) and isinstance(owner, np.ndarray) and owner.nbytes == b.nbytes:
        return b
    return b + s


class Sources:
    """Each (pattern, pose)'s :class:`FrameSource`, the last ``size`` kept; one that another thread is
    rendering is waited for, not rendered again."""

    def __init__(self, size: int, fidelity):
        self.size, self.fidelity = size, fidelity
        self._kept: OrderedDict = OrderedDict()
        self._making: dict = {}
        self._fresh: dict = {}         # key: its share of a batch's seconds, until its first frame takes it
        self._lock = threading.Lock()
        self.together = 0              # sources rendered in batches (make_together)

    def get(self, key: tuple, scene: Scene, pattern: str, stokes: bool = False) -> tuple[FrameSource,
                                                                                       float | None]:
        """(the source, the seconds its render took; None when it was kept, or made for another frame); with
        ``stokes``, one that holds (S1, S2) (a kept one without is rendered again)."""
        while True:
            with self._lock:
                if self._has(key, stokes):
                    self._kept.move_to_end(key)
                    return self._kept[key], self._fresh.pop(key, None)
                busy = self._making.get(key)
                if busy is None:
                    busy = self._making[key] = threading.Event()
                    break
            busy.wait()
        try:
            t0 = time.perf_counter()
            source = frame_source(scene, pattern, self.fidelity, stokes)
            seconds = time.perf_counter() - t0
            self._keep({key: source}, {})
        finally:
            self._done({key: busy})
        return source, seconds

    def make_together(self, scene: Scene, items: list[tuple[tuple, str]], stokes: bool = False) -> None:
        """Render the sources of ``items`` ((key, pattern), one model ``scene``) that are neither kept (with
        (S1, S2) if ``stokes``) nor being made, side by side (sim/scan_render.py ``render_scan``); each is
        charged an equal share of the batch's seconds, reported by the :meth:`get` that first takes it."""
        with self._lock:
            todo = [(k, p) for k, p in dict(items).items()
                    if k not in self._making and not self._has(k, stokes)]
            events = {k: self._making.setdefault(k, threading.Event()) for k, _ in todo}
        if not todo:
            return
        try:
            t0 = time.perf_counter()
            made = [_source(c, stokes) for c in render_scan(scene, [p for _, p in todo], self.fidelity)]
            share = (time.perf_counter() - t0) / len(todo)
            self.together += len(todo)
            self._keep({k: m for (k, _), m in zip(todo, made, strict=True)}, dict.fromkeys(events, share))
        finally:
            self._done(events)

    def _has(self, key: tuple, stokes: bool) -> bool:
        """Whether ``key``'s source is kept, with (S1, S2) if ``stokes`` (call with the lock held)."""
        return key in self._kept and (not stokes or self._kept[key].s1 is not None)

    def _keep(self, sources: dict, fresh: dict) -> None:
        with self._lock:
            self._kept.update(sources)
            self._fresh.update(fresh)
            while len(self._kept) > self.size:
                self._fresh.pop(self._kept.popitem(last=False)[0], None)

    def _done(self, events: dict) -> None:
        with self._lock:
            for k in events:
                del self._making[k]
        for e in events.values():
            e.set()


@dataclasses.dataclass(frozen=True)
class FrameJob:
    """One frame to make. ``model`` None: the ``off`` pattern, a dark frame; ``angle`` None: no analyzer;
    ``mosaic``: each pixel through its own micro-polarizer instead; ``seed``: (node seed, scan id, step,
    frame number); ``e_map``: electrons per unit radiance at the camera's exposure."""

    pattern: str
    pose: tuple
    model: Scene | None
    angle: float | None
    mosaic: MicroPolarizerArray | None
    camera: Camera
    e_map: np.ndarray = dataclasses.field(compare=False)
    seed: tuple[int, int, int, int]
    gaussian: bool

    @property
    def key(self) -> tuple:
        """What the frame depends on (the electrons map follows the exposure)."""
        return (self.pattern, self.pose, self.angle, self.mosaic is not None, self.camera.exposure_s,
                self.seed)


@dataclasses.dataclass
class FrameDone:
    """A made frame and what it cost: ``model_s`` the render's seconds (None: the source was kept)."""

    image: np.ndarray
    model_s: float | None
    resize_s: float
    sensor_s: float


def make_frame(job: FrameJob, sources: Sources) -> FrameDone:
    """The frame of ``job``: the pattern's source, the analyzer (or the mosaic), the resize to the camera,
    the EMVA 1288 sensor with the job's seed."""
    res = job.camera.resolution
    model_s = None
    t0 = time.perf_counter()
    if job.model is None:
        radiance = np.zeros((res[1], res[0]))
    else:
        source, model_s = sources.get((job.pattern, job.pose), job.model, job.pattern, job.mosaic is not None)
        t0 = time.perf_counter()
        if job.mosaic is not None:
            radiance = mosaic_radiance(*(to_camera(x, res) for x in (source.total(), source.s1, source.s2)),
                                       job.mosaic)
        elif job.angle is None:
            radiance = to_camera(source.total(), res)
        else:
            radiance = to_camera(through_analyzer(source.basis, job.angle), res)
    t1 = time.perf_counter()
    image = expose(radiance, job.camera, np.random.default_rng(list(job.seed)), electrons=job.e_map,
                   gaussian=job.gaussian)
    return FrameDone(image, model_s, t1 - t0, time.perf_counter() - t1)


def make_batch(batch: list[tuple[FrameJob, Future]], sources: Sources) -> None:
    """Make the frames of ``batch`` (one model scene; module docstring, "Together"): the sources it lacks
    rendered together, then each frame in order, its Future set as it is made (a cancelled one skipped)."""
    live = [(j, f) for j, f in batch if not f.cancelled()]
    if len(live) > 1 and live[0][0].model is not None:
        try:
            sources.make_together(live[0][0].model, [((j.pattern, j.pose), j.pattern) for j, _ in live],
                                  live[0][0].mosaic is not None)
        except Exception:  # noqa: BLE001 - each frame then renders its own source and gets its own error
            pass
    for job, future in live:
        if future.set_running_or_notify_cancel():
            try:
                future.set_result(make_frame(job, sources))
            except Exception as exc:  # noqa: BLE001 - the frame's request gets it (Simulator._answer)
                future.set_exception(exc)


def batches(jobs: list[FrameJob], size: int) -> list[list[FrameJob]]:
    """``jobs`` in order, cut into runs of at most ``size`` that share a model scene (pose and resolution;
    a dark frame alone) and the kind of frame (through the analyzer, or the mosaic)."""
    out: list[list[FrameJob]] = []
    for j in jobs:
        last = out[-1][-1] if out else None
        if (last is not None and len(out[-1]) < size and j.model is not None and last.model is not None
                and last.pose == j.pose and last.model.camera.resolution == j.model.camera.resolution
                and (last.mosaic is None) == (j.mosaic is None)):
            out[-1].append(j)
        else:
            out.append([j])
    return out


def next_jobs(job: FrameJob, depth: int, where) -> list[FrameJob]:
    """The ``depth`` frames a scan asks for after ``job`` if its analyzer, exposure and source stay: each
    the pattern that follows, the next step and frame number (fewer where the scan's patterns end);
    ``where(pattern, scan_id, step)`` gives a frame's (pose, model scene): a moving rig's changes by step."""
    out = []
    seed, pattern = job.seed, job.pattern
    for k in range(1, depth + 1):
        pattern = following(pattern) if pattern != "off" else None
        if pattern is None:
            break
        pose, model = where(pattern, seed[1], seed[2] + k)
        out.append(dataclasses.replace(job, pattern=pattern, pose=pose, model=model,
                                       seed=(seed[0], seed[1], seed[2] + k, seed[3] + k)))
    return out


@dataclasses.dataclass
class Owed:
    """A frame request not yet answered: its job, the frame's Future, when it came (perf_counter), when it
    may be answered (the node's clock), the node's deferred reply."""

    req: RenderRequest
    job: FrameJob
    future: Future
    t_start: float
    mosaic: bool
    not_before: float
    reply: object = None


class Frames:
    """The frames in flight: those made ahead (by job key) and those owed, in request order; ``stats`` (the
    node's) counts frames taken from those made ahead, renders and their seconds, kept sources, the resize
    and sensor seconds. ``threads`` workers, ``batch`` frames a batch (module docstring)."""

    def __init__(self, sources: Sources, threads: int, stats: dict, batch: int = 1):
        self.sources, self.threads, self.batch, self.stats = sources, threads, max(1, batch), stats
        self.ahead: dict = {}
        self.owed: deque[Owed] = deque()

    def start(self, job: FrameJob, where=None) -> Future:
        """The Future of ``job``'s frame (made ahead, or started now); then, with ``where``, the frames of the
        next ``threads × batch`` predicted (:func:`next_jobs`) that are missing started in batches, and the
        other frames made ahead dropped."""
        future = self.ahead.pop(job.key, None)
        self.stats["made_ahead"] += future is not None
        future = future or submit_frame(make_frame, job, self.sources)
        depth = self.threads * self.batch
        following_jobs = next_jobs(job, depth, where) if where is not None else []
        for stale in self.ahead.keys() - {j.key for j in following_jobs}:
            self.ahead.pop(stale).cancel()
        missing = [j for j in following_jobs if j.key not in self.ahead]
        busy = sum(not f.done() for f in self.ahead.values())
        if len(following_jobs) == depth and busy >= self.threads:     # only whole batches
            missing = missing[:len(missing) // self.batch * self.batch]
        for chunk in batches(missing, self.batch):
            pairs = [(j, Future()) for j in chunk]
            self.ahead.update((j.key, f) for j, f in pairs)
            submit_frame(make_batch, pairs, self.sources)
        return future

    def count(self, done: FrameDone) -> None:
        """Add a made frame's costs to :attr:`stats`."""
        if done.model_s is None:
            self.stats["cache_hits"] += 1
        else:
            self.stats["renders"] += 1
            self.stats["model_s"] += done.model_s
        self.stats["resize_s"] += done.resize_s
        self.stats["sensor_s"] += done.sensor_s

    def ready(self, now: float) -> Owed | None:
        """The first owed frame if it is made and may be answered at ``now``, taken off the queue."""
        if self.owed and self.owed[0].future.done() and now >= self.owed[0].not_before:
            return self.owed.popleft()
        return None

    def close(self) -> list[Owed]:
        """Cancel every frame in flight; the owed ones, to be answered with an error."""
        for future in self.ahead.values():
            future.cancel()
        owed, self.owed = list(self.owed), deque()
        for o in owed:
            o.future.cancel()
        return owed
