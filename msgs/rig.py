"""The rig's device messages: the analyzer mount, the polarizer's calibration service, the simulator's
requests and fault commands. Declared here, not in the nodes, so that tools (``record``, ``topic echo``) and
other nodes know them without importing a node."""

from __future__ import annotations

from dataclasses import field

from polarstripe.msgs.base import Message, message


@message("analyzer_mount")
class AnalyzerMount(Message):
    """Put the analyzer in the optical path (``inserted``) or take it out (unpolarized methods)."""

    inserted: bool


#: scan ids of calibration frames start here (the emitter counts its scans from 1)
CALIBRATION_SCAN_ID = 2**30


@message("polarizer_calibrate_request")
class CalibrateRequest(Message):
    """Find E_b: ``angles_deg`` to sample (empty: the node's ``calibrate_angles_deg``), the object-free
    ``roi`` (row0, row1, col0, col1; empty: the node's ``calibrate_roi``, or the whole frame), and whether to
    turn the analyzer to the result afterwards."""

    angles_deg: list[float] = field(default_factory=list)
    roi: list[int] = field(default_factory=list)
    apply: bool = True


@message("polarizer_calibration")
class Calibration(Message):
    """The analyzer angle of least backscatter ``angle_deg`` [deg, within the stage's limits] or why not; the
    measured angles and the region's mean [DN, offset subtracted] at each."""

    ok: bool
    angle_deg: float | None = None
    detail: str = ""
    angles_deg: list[float] = field(default_factory=list)
    means_dn: list[float] = field(default_factory=list)


@message("sim_render_request")
class RenderRequest(Message):
    """Ask the simulator for one frame of ``pattern`` (``flood``, ``stripe:K/N``, ``checker:SIZE:SHIFT``,
    ``off``); ``analyzer`` False takes it with no analyzer in the path; ``exposure_s`` None uses the
    simulator's."""

    pattern: str
    analyzer: bool = True
    scan_id: int = 0
    step: int = 0
    exposure_s: float | None = None


@message("sim_fault")
class SimFault(Message):
    """A fault injection command for the simulator, e.g. ``"never_settle on"``, ``"camera_lost on"``."""

    command: str


#: command -> what it does (``simulator/fault`` and the ``faults`` param)
FAULT_COMMANDS = {
    "never_settle": "on|off: the drive hunts around its target and never reports target reached",
    "emcy": "[CODE]: the drive faults and sends an EMCY (default 0x8611)",
    "heartbeat_stop": "[SECONDS]: the drive's heartbeat stops (for SECONDS, or until heartbeat_resume)",
    "heartbeat_resume": ": the heartbeat comes back",
    "bus_off": "SECONDS: an error frame 'bus-off', silence, then 'restarted'",
    "position_limit": "MIN MAX: the drive's software position limit [counts]",
    "camera_lost": "on|off: simulator/render answers with an error (the camera is gone)",
    "frame_delay": "SECONDS: each frame is answered this long after its request (a hung camera; 0 ends it)",
}
