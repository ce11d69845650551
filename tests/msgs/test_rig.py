"""The rig's device messages (msgs/rig.py): they travel (test_codec.py covers ALL_TYPES only), their
signatures and the fault commands are the ones docs/architecture.md gives, calibration scan ids stay apart."""

from __future__ import annotations

import ast
import dataclasses
import re
from pathlib import Path

import jsonschema
import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from polarstripe import msgs
from polarstripe.msgs import (
    ALL_TYPES,
    CALIBRATION_SCAN_ID,
    FAULT_COMMANDS,
    REGISTRY,
    AnalyzerMount,
    CalibrateRequest,
    Calibration,
    Frame,
    Header,
    RenderRequest,
    SimFault,
    decode,
    encode,
    json_schema,
    pack,
    unpack,
)

RIG_TYPES = (AnalyzerMount, CalibrateRequest, Calibration, RenderRequest, SimFault)
ARCHITECTURE = (Path(__file__).resolve().parents[2] / "docs" / "architecture.md").read_text()

_text = st.text(max_size=12)
_floats = st.floats(allow_nan=False)
_STRATEGIES = {
    AnalyzerMount: st.builds(AnalyzerMount, inserted=st.booleans()),
    CalibrateRequest: st.builds(CalibrateRequest, angles_deg=st.lists(_floats, max_size=6),
                                roi=st.lists(st.integers(-(2**31), 2**31), max_size=4), apply=st.booleans()),
    Calibration: st.builds(Calibration, ok=st.booleans(), angle_deg=st.none() | _floats, detail=_text,
                           angles_deg=st.lists(_floats, max_size=6), means_dn=st.lists(_floats, max_size=6)),
    RenderRequest: st.builds(RenderRequest, pattern=_text, analyzer=st.booleans(),
                             scan_id=st.integers(0, 2**62), step=st.integers(0, 2**31),
                             exposure_s=st.none() | _floats),
    SimFault: st.builds(SimFault, command=_text),
}


def _with_header(msg, stamp):
    return dataclasses.replace(msg, header=Header(stamp_ns=stamp, seq=3, frame_id="rig"))


@pytest.mark.parametrize("cls", RIG_TYPES, ids=lambda c: c.TYPE)
@settings(max_examples=30, deadline=None)
@given(data=st.data())
def test_rig_messages_round_trip_and_match_their_schema(cls, data):
    msg = _with_header(data.draw(_STRATEGIES[cls]), data.draw(st.integers(1, 2**62)))
    frames = [bytes(memoryview(f).cast("B")) for f in encode(msg, topic="/rig/x")]
    assert decode(frames, topic="/rig/x", expect=cls) == msg
    blob = pack(msg)
    assert unpack(blob, expect=cls) == msg
    doc = msgpack.unpackb(blob, raw=False)
    jsonschema.validate(doc, json_schema(cls))


def test_rig_types_are_registered_exported_and_apart_from_the_core_types():
    for cls in RIG_TYPES:
        assert REGISTRY[cls.TYPE] is cls and getattr(msgs, cls.__name__) is cls
    assert not set(RIG_TYPES) & set(ALL_TYPES)


def _documented_signature(name: str) -> list[tuple[str, object]]:
    """[(field, default or MISSING)] of ``Name(a, b=1, c: bool)`` as the docs write it."""
    m = re.search(rf"`{name}\(([^`]*)\)`", ARCHITECTURE)
    assert m, f"docs/architecture.md does not show {name}(...)"
    out = []
    for item in m[1].split(","):
        field, _, default = item.strip().partition("=")
        field = field.split(":")[0].strip()
        out.append((field, ast.literal_eval(default) if default else dataclasses.MISSING))
    return out


@pytest.mark.parametrize("cls", RIG_TYPES, ids=lambda c: c.TYPE)
def test_signatures_are_the_documented_ones(cls):
    documented = _documented_signature(cls.__name__)
    assert [f for f, _ in documented] == [n for n, _ in cls.FIELDS]
    declared = {f.name: f for f in dataclasses.fields(cls)}
    for name, default in documented:
        if default is dataclasses.MISSING:
            continue  # the docs leave some defaults out (Calibration's)
        f = declared[name]
        actual = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        assert actual == default, name
    if cls is not SimFault:  # the docs name every wire name but sim_fault's
        assert f"`{cls.TYPE}`" in ARCHITECTURE


def test_fault_commands_are_the_documented_ones():
    m = re.search(r"\(`SimFault\(command\)` → `Ack`: (.*?); the\s", ARCHITECTURE, re.S)
    assert m, "docs/architecture.md does not list the simulator's fault commands"
    documented = [item.split()[0] for item in re.findall(r"`([^`]+)`", m[1])]
    assert documented == list(FAULT_COMMANDS)
    for name, text in FAULT_COMMANDS.items():
        assert re.fullmatch(r"[a-z_]+", name)
        assert ": " in text or text.startswith(": "), name  # "ARGS: what it does"


def test_calibration_scan_ids_are_beyond_any_emitter_scan_and_travel():
    assert CALIBRATION_SCAN_ID == 2**30
    frame = Frame(image=np.zeros((1, 1), np.uint16), exposure_s=0.01,
                  scan_id=CALIBRATION_SCAN_ID + 5)
    back = decode([bytes(memoryview(f).cast("B")) for f in encode(frame)], expect=Frame)
    assert back.scan_id - CALIBRATION_SCAN_ID == 5


def test_defaults_of_the_requests():
    c = CalibrateRequest()
    assert (c.angles_deg, c.roi, c.apply) == ([], [], True)
    c.angles_deg.append(1.0)
    assert CalibrateRequest().angles_deg == []
    r = RenderRequest(pattern="flood")
    assert (r.analyzer, r.scan_id, r.step, r.exposure_s) == (True, 0, 0, None)

