"""The rig's message types, each declared once. Units are in the field names (SI, degrees only for angles
that a person types). Every message also has ``header`` (:class:`~polarstripe.msgs.base.Header`)."""

from __future__ import annotations

from dataclasses import field
from typing import Any, Literal

import numpy as np
from polarstripe.msgs.base import Message, message
from polarstripe.msgs.patterns import PatternSpec
from polarstripe.msgs.patterns import parse as parse_pattern


@message("frame", version=2, older={1: 8})
class Frame(Message):
    """One camera image and how it was taken.

    ``image`` is (h, w) or (h, w, c), usually uint16 DN with ``bit_depth`` significant bits. ``pattern``
    is the emitter's tag of what was lit (e.g. ``"flood"``, ``"stripe:3/30"``); ``polarizer_deg`` is the
    analyzer angle [deg] or None without a polarizer; ``scan_id``/``step`` match the frame to the emitter's
    request. ``mosaic_deg``: a polarization camera's frame, the raw 2×2 micro-polarizer mosaic, gives its
    4 angles [deg] row-major from the top-left pixel (Sony: 90, 45, 135, 0); empty for any other frame.
    Version 2 added ``mosaic_deg`` (version 1 reads with it empty).
    """

    image: np.ndarray
    exposure_s: float
    gain: float = 1.0
    bit_depth: int = 12
    pattern: str = ""
    polarizer_deg: float | None = None
    scan_id: int = 0
    step: int = 0
    mosaic_deg: list[float] = field(default_factory=list)


@message("pattern", version=4, older={1: 7, 2: 9, 3: 10})
class Pattern(Message):
    """What the emitter lights now: flood, stripe ``index`` of ``count`` (``size`` px wide), a checker of
    ``size`` px shifted by ``shift`` px, Gray code bit ``index`` of the ``axis`` (``col``/``row``, its
    ``inverse``, XOR the column code's bit ``xor`` when ≥ 0; msgs/patterns.py), or nothing; a stripe lights
    ``sheets`` evenly spaced sheets at once (frame ``index`` of ⌈count/sheets⌉). Version 2 added ``axis`` and
    ``inverse``, version 3 ``xor``, version 4 ``sheets`` (older versions read with their defaults; a reader
    of version 3 refuses a version 4 message: unknown schema version)."""

    kind: Literal["flood", "stripe", "checker", "off", "gray"]
    index: int = 0
    count: int = 0
    size: int = 0
    shift: int = 0
    scan_id: int = 0
    step: int = 0
    axis: str = ""
    inverse: bool = False
    xor: int = -1
    sheets: int = 1

    @classmethod
    def of(cls, pattern, scan_id: int = 0, step: int = 0) -> Pattern:
        """The message of a pattern tag (``"stripe:3/30"``) or
        :class:`~polarstripe.msgs.patterns.PatternSpec`; ``PatternError`` if it describes no pattern."""
        p = parse_pattern(pattern)
        return cls(kind=p.kind, index=p.index, count=p.count, size=p.size, shift=p.shift, scan_id=scan_id,
                   step=step, axis=p.axis, inverse=p.inverse, xor=p.xor, sheets=p.sheets)

    def spec(self) -> PatternSpec:
        """The checked pattern; ``PatternError`` if the fields describe none."""
        return parse_pattern(self)


@message("scan_event", version=2, older={1: 6})
class ScanEvent(Message):
    """A scan starts, is done, or stopped on a fault (``detail`` says why). A stripe scan lights ``sheets``
    sheets per frame (version 2; version 1 reads as one)."""

    scan_id: int
    event: Literal["start", "done", "fault"]
    method: str = ""
    stripes: int = 0
    analyzer_deg: list[float] = field(default_factory=list)
    detail: str = ""
    sheets: int = 1


@message("polarizer_command")
class PolarizerCommand(Message):
    """Turn the analyzer to ``target_deg`` [deg]."""

    target_deg: float


@message("polarizer_state")
class PolarizerState(Message):
    """Where the analyzer is [deg], where it is going, whether it has settled, and a fault text ("" if
    none)."""

    angle_deg: float
    target_deg: float
    settled: bool
    fault: str = ""


@message("composite")
class Composite(Message):
    """The result of a scan: named images (e.g. ``"max"``, ``"min"``, ``"descattered"``) and quality
    metrics."""

    images: dict[str, np.ndarray]
    method: str
    scan_id: int = 0
    metrics: dict[str, Any] = field(default_factory=dict)


@message("medium_estimate", version=2, older={1: 3})
class MediumEstimate(Message):
    """The medium as measured in situ: backscatter degree of polarization ``p`` and, when known, the
    extinction coefficient ``sigma_t_per_m`` [1/m] and the phase function's mean cosine, each with its 1σ
    uncertainty (None: not estimated). ``reason`` non-empty: the fit could not estimate σ_t and the mean
    cosine, and says why (their fields are None then). Version 2 added the fields after ``scan_id``
    (version 1 reads with their defaults)."""

    p: float
    sigma_t_per_m: float | None = None
    scan_id: int = 0
    mean_cosine: float | None = None
    p_std: float | None = None
    sigma_t_std: float | None = None
    mean_cosine_std: float | None = None
    reason: str = ""


@message("plan", version=2, older={1: 5})
class Plan(Message):
    """The planner's choice: modality, camera–source separation [m], scan type, per-stripe optima, the
    quality curves it was chosen from (named arrays, e.g. ``"separation_m"``, ``"quality"``) and the sheets
    per stripe frame (version 2; version 1 reads as one)."""

    modality: Literal["flood", "stripes"]
    separation_m: float
    scan_type: str = ""
    stripe_optima: list[float] = field(default_factory=list)
    curves: dict[str, np.ndarray] = field(default_factory=dict)
    sheets: int = 1


@message("log")
class Log(Message):
    """One log line of a node (``level`` is a Python logging level name)."""

    level: Literal["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"]
    node: str
    text: str


@message("heartbeat")
class Heartbeat(Message):
    """A node is alive: its name, process id, uptime [s] and counters (received, published, bad, gaps …).

    The counters also carry ``incarnation`` (0 at the first start, the launcher's respawn count after),
    ``heartbeat_ms`` (the period) and, in the last beat of an orderly exit, ``exiting`` = 1
    (runtime/liveness.py). They ride in ``counters`` so that the schema (version 1) and every recording made
    before stay as they were; a beat without them reads as incarnation 0."""

    node: str
    pid: int
    uptime_s: float
    counters: dict[str, int] = field(default_factory=dict)

    @property
    def incarnation(self) -> int:
        return int(self.counters.get("incarnation", 0))


# ---- service requests and replies ------------------------------------------------------------------------
@message("empty")
class Empty(Message):
    """A request or reply with no content."""


@message("ack")
class Ack(Message):
    """A service reply: did it work, and a short text."""

    ok: bool
    detail: str = ""


@message("scan_request", version=2, older={1: 3})
class ScanRequest(Message):
    """Ask the emitter for a scan: ``method`` (e.g. ``"flood"``, ``"stripes"``), the stripe count, the
    analyzer angles [deg] to scan at (empty: the current angle) and the sheets per frame of a stripe scan
    (version 2; 0, and version 1: the emitter's ``sheets`` param)."""

    method: str
    stripes: int = 0
    analyzer_deg: list[float] = field(default_factory=list)
    sheets: int = 0


@message("frame_request")
class FrameRequest(Message):
    """Ask the grabber (or simulator) for one frame of ``scan_id``/``step`` showing ``pattern``."""

    scan_id: int = 0
    step: int = 0
    pattern: str = ""
    exposure_s: float | None = None


ALL_TYPES: tuple[type[Message], ...] = (
    Frame,
    Pattern,
    ScanEvent,
    PolarizerCommand,
    PolarizerState,
    Composite,
    MediumEstimate,
    Plan,
    Log,
    Heartbeat,
    Empty,
    Ack,
    ScanRequest,
    FrameRequest,
)
