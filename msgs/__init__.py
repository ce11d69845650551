"""The message vocabulary: typed messages, MessagePack codec, zero-copy arrays, JSON Schemas.

See docs/architecture.md, "Bus, messages and nodes"."""

from polarstripe.msgs.base import REGISTRY, Header, Message, MessageError, message
from polarstripe.msgs.codec import DEFAULT_MAX_BYTES, decode, describe, encode, pack, unpack
from polarstripe.msgs.depth import DepthMap
from polarstripe.msgs.methods import METHOD_NAMES, Method
from polarstripe.msgs.patterns import PatternError, PatternSpec
from polarstripe.msgs.rig import (
    CALIBRATION_SCAN_ID,
    FAULT_COMMANDS,
    AnalyzerMount,
    CalibrateRequest,
    Calibration,
    RenderRequest,
    SimFault,
)
from polarstripe.msgs.schema import json_schema
from polarstripe.msgs.types import (
    ALL_TYPES,
    Ack,
    Composite,
    Empty,
    Frame,
    FrameRequest,
    Heartbeat,
    Log,
    MediumEstimate,
    Pattern,
    Plan,
    PolarizerCommand,
    PolarizerState,
    ScanEvent,
    ScanRequest,
)

__all__ = [
    "CALIBRATION_SCAN_ID",
    "FAULT_COMMANDS",
    "METHOD_NAMES",
    "AnalyzerMount",
    "CalibrateRequest",
    "Calibration",
    "Method",
    "PatternError",
    "PatternSpec",
    "RenderRequest",
    "SimFault",
    "ALL_TYPES",
    "DEFAULT_MAX_BYTES",
    "REGISTRY",
    "Ack",
    "Composite",
    "DepthMap",
    "Empty",
    "Frame",
    "FrameRequest",
    "Header",
    "Heartbeat",
    "Log",
    "MediumEstimate",
    "Message",
    "MessageError",
    "Pattern",
    "Plan",
    "PolarizerCommand",
    "PolarizerState",
    "ScanEvent",
    "ScanRequest",
    "decode",
    "describe",
    "encode",
    "json_schema",
    "message",
    "pack",
    "unpack",
]
