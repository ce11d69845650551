"""What a recorded or live message looks like to the robotics tools: one message becomes a few *views*
(an image, a camera calibration, transforms, a log line, a joint, a record of plottable numbers), and each
exporter maps the views to its own types (:mod:`polarstripe.nodes.ros2_schemas` to ROS 2 messages,
:mod:`polarstripe.nodes.foxglove_schemas` to Foxglove schemas). One mapping, so the ROS 2 bag, the Foxglove
MCAP and the live Foxglove bridge show the same topics.

=========================  ====================================================================
message on ``T``           views
=========================  ====================================================================
``Frame``                  ``T/image`` image, ``T/camera_info`` calibration, ``T/info`` FrameInfo
``Pattern``                ``T/image`` the projector image, ``T/camera_info``, ``T/info`` PatternInfo
``PolarizerState``         ``T`` PolarizerState, ``T/joint_states`` joint ``analyzer`` [rad]
``Composite``              ``T/<name>`` per image, ``T/metrics`` CompositeMetrics
``DepthMap``               ``T/image`` depth [m] (NaN: none), ``T/points`` the points, ``T`` packed
``Log``                    ``T`` log line
``ScanEvent`` …            ``T`` a record of the same name (see :data:`RECORDS`)
anything else              ``T`` packed (its MessagePack form)
(geometry)                 ``/tf_static`` transforms tank → camera → polarizer, tank → projector
=========================  ====================================================================

A record's fields are declared once in :data:`RECORDS` (field, type); the ROS 2 message definitions
(``polarstripe_msgs/msg/<Kind>``) and the JSON Schemas (``polarstripe.<Kind>``) are generated from it.
Floats that are None in a message (no analyzer, unknown σ_t) are NaN in a record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from polarstripe.msgs import (
    REGISTRY,
    Composite,
    DepthMap,
    Frame,
    Heartbeat,
    Log,
    MediumEstimate,
    Message,
    Pattern,
    Plan,
    PolarizerCommand,
    PolarizerState,
    ScanEvent,
    pack,
)
from polarstripe.nodes.drivers.display import render_pattern
from polarstripe.nodes.drivers.errors import DriverValueError
from polarstripe.nodes.rig_geometry import CAMERA, PROJECTOR, Intrinsics, Pose, RigGeometry, pinhole

TF_STATIC = "/tf_static"
DEFAULT_PROJECTOR = (1024, 768)  # px, without a scene (sim.scene.Projector's default)

#: kind -> ((field, type), ...); types: string, bool, uint32, int64, float64, and arrays of those ("[]"),
#: uint8[] (bytes), or a nested record kind ("Curve[]"). Records in NESTED have no header.
RECORDS: dict[str, tuple[tuple[str, str], ...]] = {
    "FrameInfo": (("pattern", "string"), ("polarizer_deg", "float64"), ("exposure_s", "float64"),
                  ("gain", "float64"), ("bit_depth", "uint32"), ("scan_id", "uint32"), ("step", "uint32"),
                  ("stamp_ns", "int64"), ("seq", "uint32")),
    "PatternInfo": (("tag", "string"), ("kind", "string"), ("index", "uint32"), ("count", "uint32"),
                    ("size", "uint32"), ("shift", "uint32"), ("scan_id", "uint32"), ("step", "uint32")),
    "PolarizerState": (("angle_deg", "float64"), ("target_deg", "float64"), ("settled", "bool"),
                       ("fault", "string")),
    "PolarizerCommand": (("target_deg", "float64"),),
    "ScanEvent": (("scan_id", "uint32"), ("event", "string"), ("method", "string"), ("stripes", "uint32"),
                  ("analyzer_deg", "float64[]"), ("detail", "string"), ("sheets", "uint32")),
    "CompositeMetrics": (("method", "string"), ("scan_id", "uint32"), ("contrast", "float64"),
                         ("error_vs_truth", "float64"), ("p", "float64"), ("dark_offset_dn", "float64"),
                         ("names", "string[]"), ("values", "float64[]")),
    "MediumEstimate": (("p", "float64"), ("sigma_t_per_m", "float64"), ("scan_id", "uint32"),
                       ("mean_cosine", "float64"), ("p_std", "float64"), ("sigma_t_std", "float64"),
                       ("mean_cosine_std", "float64"), ("reason", "string")),
    "Curve": (("name", "string"), ("values", "float64[]")),
    "Plan": (("modality", "string"), ("separation_m", "float64"), ("scan_type", "string"),
             ("stripe_optima", "float64[]"), ("curves", "Curve[]"), ("sheets", "uint32")),
    "Heartbeat": (("node", "string"), ("pid", "uint32"), ("uptime_s", "float64"),
                  ("counter_names", "string[]"), ("counter_values", "int64[]")),
    "Packed": (("type", "string"), ("version", "uint32"), ("msgpack", "uint8[]")),
}
NESTED = frozenset({"Curve"})


# ---- views -------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Image:
    """A 2-D (or h×w×c) image; each exporter picks the encoding for its dtype."""

    topic: str
    stamp_ns: int
    frame_id: str
    array: np.ndarray


@dataclass(frozen=True)
class Calibration:
    """Pinhole intrinsics of the images on a sibling topic."""

    topic: str
    stamp_ns: int
    frame_id: str
    intrinsics: Intrinsics


@dataclass(frozen=True)
class Transforms:
    """Poses of frames (latched: ``/tf_static``)."""

    topic: str
    stamp_ns: int
    poses: tuple[Pose, ...]


@dataclass(frozen=True)
class LogLine:
    """One log line of a node (``level``: a Python logging level name)."""

    topic: str
    stamp_ns: int
    level: str
    node: str
    text: str


@dataclass(frozen=True)
class Joint:
    """Joint positions [rad] by name."""

    topic: str
    stamp_ns: int
    names: tuple[str, ...]
    positions: tuple[float, ...]


@dataclass(frozen=True)
class Record:
    """Plottable values of kind ``kind`` (fields as declared in :data:`RECORDS`)."""

    topic: str
    stamp_ns: int
    kind: str
    values: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Packed:
    """A message with no better view: its type, version and MessagePack form (``msg`` if decoded)."""

    topic: str
    stamp_ns: int
    type: str
    version: int
    payload: bytes
    msg: Message | None = None


@dataclass(frozen=True)
class Points:
    """A point cloud: ``points`` (n, 3) float32 [m] in ``frame_id`` (n ≥ 1)."""

    topic: str
    stamp_ns: int
    frame_id: str
    points: np.ndarray


View = Image | Calibration | Transforms | LogLine | Joint | Record | Points | Packed


def _f(v) -> float:
    return math.nan if v is None else float(v)


def _u32(v) -> int:
    return int(v) & 0xFFFFFFFF


def metrics_values(method: str, scan_id: int, metrics: dict) -> dict:
    """The CompositeMetrics record of a composite: the well-known metrics (NaN if absent) and every numeric
    metric by name."""
    numeric = {k: float(v) for k, v in metrics.items()
               if isinstance(v, int | float | np.number) and not isinstance(v, bool)}
    return {"method": method, "scan_id": _u32(scan_id),
            **{k: _f(numeric.get(k)) for k in ("contrast", "error_vs_truth", "p", "dark_offset_dn")},
            "names": list(numeric), "values": list(numeric.values())}


class RigViews:
    """Turns messages into views (module docstring). ``geometry`` None: no tf and no calibrations."""

    def __init__(self, geometry: RigGeometry | None = None):
        self.geometry = geometry
        self._patterns: dict[tuple, np.ndarray] = {}
        self._separation: float | None = None
        self.started = False

    def start(self, stamp_ns: int) -> list[View]:
        """The views that open an export or a live session: the rig's poses on ``/tf_static``."""
        self.started = True
        if self.geometry is None:
            return []
        return [Transforms(TF_STATIC, stamp_ns, tuple(self.geometry.poses()))]

    def _moved(self, stamp_ns: int, separation_m) -> list[View]:
        """Move the source (a truth message's ``separation_m``); the new poses if they changed."""
        if self.geometry is None or not isinstance(separation_m, int | float):
            return []
        if separation_m == self._separation:
            return []
        self._separation = float(separation_m)
        self.geometry = self.geometry.separated(self._separation)
        return self.start(stamp_ns) if self.started else []

    def place(self, separation_m: float) -> None:
        """Put the source at ``separation_m`` before :meth:`start` (a recording's first known distance)."""
        self._moved(0, separation_m)

    def pattern_image(self, msg: Pattern) -> np.ndarray | None:
        """The projector image of a pattern message (cached per pattern), None if it describes none."""
        w, h = self.geometry.projector_size if self.geometry else DEFAULT_PROJECTOR
        key = (msg.kind, msg.index, msg.count, msg.size, msg.shift, msg.sheets, w, h)
        img = self._patterns.get(key)
        if img is None:
            try:
                img = render_pattern(msg, w, h)
            except DriverValueError:
                return None
            if len(self._patterns) < 256:
                self._patterns[key] = img
        return img

    def views(self, topic: str, stamp_ns: int, msg: Message) -> list[View]:
        """The views of ``msg`` received on ``topic``, stamped ``stamp_ns``."""
        out: list[View] = [] if self.started else self.start(stamp_ns)
        if isinstance(msg, Frame):
            out.append(Image(f"{topic}/image", stamp_ns, msg.header.frame_id or CAMERA, msg.image))
            if self.geometry is not None:
                h, w = msg.image.shape[:2]
                out.append(Calibration(f"{topic}/camera_info", stamp_ns, msg.header.frame_id or CAMERA,
                                       self.geometry.camera(w, h)))
            out.append(Record(f"{topic}/info", stamp_ns, "FrameInfo", {
                "pattern": msg.pattern, "polarizer_deg": _f(msg.polarizer_deg), "exposure_s": msg.exposure_s,
                "gain": msg.gain, "bit_depth": _u32(msg.bit_depth), "scan_id": _u32(msg.scan_id),
                "step": _u32(msg.step), "stamp_ns": msg.header.stamp_ns, "seq": _u32(msg.header.seq)}))
        elif isinstance(msg, Pattern):
            img = self.pattern_image(msg)
            if img is not None:
                out.append(Image(f"{topic}/image", stamp_ns, PROJECTOR, img))
                intr = self.geometry.projector() if self.geometry else pinhole(60.0, *DEFAULT_PROJECTOR)
                out.append(Calibration(f"{topic}/camera_info", stamp_ns, PROJECTOR, intr))
            tag = str(msg.spec()) if img is not None else msg.kind
            out.append(Record(f"{topic}/info", stamp_ns, "PatternInfo", {
                "tag": tag, "kind": msg.kind, **{k: _u32(getattr(msg, k)) for k in
                                                 ("index", "count", "size", "shift", "scan_id", "step")}}))
        elif isinstance(msg, PolarizerState):
            out.append(Record(topic, stamp_ns, "PolarizerState", {
                "angle_deg": msg.angle_deg, "target_deg": msg.target_deg, "settled": msg.settled,
                "fault": msg.fault}))
            angle = (math.radians(msg.angle_deg),)
            out.append(Joint(f"{topic}/joint_states", stamp_ns, ("analyzer",), angle))
        elif isinstance(msg, Composite):
            if msg.method == "truth":
                out += self._moved(stamp_ns, msg.metrics.get("separation_m"))
            for name, img in msg.images.items():
                if img.ndim in (2, 3) and img.size:
                    out.append(Image(f"{topic}/{name}", stamp_ns, msg.header.frame_id or CAMERA, img))
            out.append(Record(f"{topic}/metrics", stamp_ns, "CompositeMetrics",
                              metrics_values(msg.method, msg.scan_id, msg.metrics)))
        elif isinstance(msg, DepthMap):
            frame_id = msg.header.frame_id or CAMERA
            out.append(Image(f"{topic}/image", stamp_ns, frame_id, np.asarray(msg.depth_m, np.float32)))
            if msg.points_m is not None and len(msg.points_m):
                points = np.asarray(msg.points_m, np.float32)
                out.append(Points(f"{topic}/points", stamp_ns, frame_id, points))
            out.append(Packed(topic, stamp_ns, msg.TYPE, msg.VERSION, pack(msg, topic=topic), msg))
        elif isinstance(msg, Log):
            out.append(LogLine(topic, stamp_ns, msg.level, msg.node, msg.text))
        elif isinstance(msg, ScanEvent):
            out.append(Record(topic, stamp_ns, "ScanEvent", {
                "scan_id": _u32(msg.scan_id), "event": msg.event, "method": msg.method,
                "stripes": _u32(msg.stripes), "analyzer_deg": list(msg.analyzer_deg), "detail": msg.detail,
                "sheets": _u32(msg.sheets)}))
        elif isinstance(msg, PolarizerCommand):
            out.append(Record(topic, stamp_ns, "PolarizerCommand", {"target_deg": msg.target_deg}))
        elif isinstance(msg, MediumEstimate):
            out.append(Record(topic, stamp_ns, "MediumEstimate", {
                "p": msg.p, "sigma_t_per_m": _f(msg.sigma_t_per_m), "scan_id": _u32(msg.scan_id),
                **{k: _f(getattr(msg, k))
                   for k in ("mean_cosine", "p_std", "sigma_t_std", "mean_cosine_std")},
                "reason": msg.reason}))
        elif isinstance(msg, Plan):
            out.append(Record(topic, stamp_ns, "Plan", {
                "modality": msg.modality, "separation_m": msg.separation_m, "scan_type": msg.scan_type,
                "stripe_optima": list(msg.stripe_optima),
                "curves": [{"name": k, "values": np.asarray(v, float).ravel().tolist()}
                           for k, v in msg.curves.items()], "sheets": _u32(msg.sheets)}))
        elif isinstance(msg, Heartbeat):
            out.append(Record(topic, stamp_ns, "Heartbeat", {
                "node": msg.node, "pid": _u32(msg.pid), "uptime_s": msg.uptime_s,
                "counter_names": list(msg.counters),
                "counter_values": [int(v) for v in msg.counters.values()]}))
        else:
            out.append(Packed(topic, stamp_ns, msg.TYPE, msg.VERSION, pack(msg, topic=topic), msg))
        return out


class ViewGate:
    """What a bridge sends of the views: images only if ``images``, at most ``image_max_hz`` per topic (0:
    every one); the newest ``/tf_static`` is kept in ``static`` for subscribers that join later."""

    def __init__(self, static: list[View], images: bool = True, image_max_hz: float = 0.0):
        self.static, self.images, self.image_max_hz = static, images, image_max_hz
        self._last_image: dict[str, float] = {}

    def select(self, views: list[View], now: float) -> list[View]:
        """The views to send at monotonic time ``now`` [s]."""
        out = []
        for v in views:
            if isinstance(v, Transforms) and v.topic == TF_STATIC:
                self.static = [v]
            if isinstance(v, Image):
                if not self.images:
                    continue
                hz = self.image_max_hz
                if hz > 0 and now - self._last_image.get(v.topic, -1e9) < 1.0 / hz:
                    continue
                self._last_image[v.topic] = now
            out.append(v)
        return out


LATEST = (Frame, Pattern)  # big and frequent: a bridge forwards the newest only


def subscribe_bridged(node, topics: list[str], known: dict, forward, verb: str) -> list[str]:
    """Subscribe a bridge ``node`` to each of ``topics`` (full names) whose type the launch graph ``known``
    names and this build knows, ``forward(topic, msg)`` on each message (the newest only for :data:`LATEST`
    types); any other topic is one warning, "not {verb} TOPIC". Returns the topics subscribed."""
    subscribed = []
    for topic in topics:
        cls = REGISTRY.get(known.get(topic, {}).get("type", ""))
        if cls is None:
            node.log.warning("not %s %s: unknown message type", verb, topic)
            continue
        mode = "latest" if issubclass(cls, LATEST) else "all"
        node.subscribe(topic, lambda m, t=topic: forward(t, m), msg_type=cls, mode=mode)
        subscribed.append(topic)
    return subscribed

