"""The simulator node's vocabulary: the requests it serves (:class:`RenderRequest`, :class:`SimFault`), the
fault commands it knows (:data:`FAULT_COMMANDS`), its error type and the ``resolution`` param's parser. Light
to import: the grabber and the sim camera build requests without loading the model."""

from __future__ import annotations

from polarstripe.msgs import message
from polarstripe.msgs.base import Message
from polarstripe.sim.scene import SceneError, parse_size


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
    "frame_delay": "SECONDS: each render waits this long first (a hung camera; 0 ends it)",
}


class SimulatorError(SceneError):
    """A simulator request or parameter that cannot be served; the text names the field and the value."""


def parse_resolution(text: str) -> tuple[int, int] | None:
    if not text:
        return None
    w, h = parse_size(text)
    if w < 2 or h < 2:
        raise ValueError(f"resolution {text!r}: need at least 2x2")
    return w, h
