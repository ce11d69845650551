"""The rig's message types (msgs/types.py): the table in docs/architecture.md is the contract (wire names,
fields in order, defaults), the registry holds each type once, and Pattern converts to and from the pattern
grammar. Round trips of every type are in test_codec.py."""

from __future__ import annotations

import ast
import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from polarstripe import msgs
from polarstripe.msgs import (
    ALL_TYPES,
    REGISTRY,
    Composite,
    Pattern,
    PatternError,
    PatternSpec,
    Plan,
    ScanEvent,
    decode,
    encode,
)
from polarstripe.msgs.patterns import parse

ARCHITECTURE = Path(__file__).resolve().parents[2] / "docs" / "architecture.md"
_ROW = re.compile(r"^\| `(\w+)` \(`(\w+)`\) \| (.*) \|$", re.M)
_FIELD = re.compile(r"`(\w+)(?::[^`=]*)?(?:=([^`]*))?`")


def _documented() -> dict[str, tuple[str, list[tuple[str, str | None]]]]:
    """class name -> (wire name, [(field, default text or None)]) from the docs' message table."""
    out = {}
    for cls_name, wire, fields in _ROW.findall(ARCHITECTURE.read_text()):
        out[cls_name] = (wire, [(m[1], m[2] if "=" in m[0] else None) for m in _FIELD.finditer(fields)])
    return out


def test_the_documented_table_lists_exactly_the_rig_types():
    assert set(_documented()) == {cls.__name__ for cls in ALL_TYPES}


@pytest.mark.parametrize("cls", ALL_TYPES, ids=lambda c: c.TYPE)
def test_each_type_matches_its_row_in_the_docs(cls):
    wire, fields = _documented()[cls.__name__]
    assert cls.TYPE == wire
    assert [name for name, _ in fields] == [name for name, _ in cls.FIELDS]
    declared = {f.name: f for f in dataclasses.fields(cls)}
    for name, default in fields:
        f = declared[name]
        if default is None:
            assert f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING, name
        else:
            value = ast.literal_eval(default.replace("\\|", "|"))
            actual = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            assert actual == value and type(actual) is type(value), name


def test_every_type_is_registered_once_and_exported():
    assert len({cls.TYPE for cls in ALL_TYPES}) == len(ALL_TYPES)
    for cls in ALL_TYPES:
        assert REGISTRY[cls.TYPE] is cls
        assert getattr(msgs, cls.__name__) is cls and cls.__name__ in msgs.__all__
        appended = {"medium_estimate": 2, "frame": 2, "pattern": 4, "scan_event": 2, "scan_request": 2,
                    "plan": 2}  # versions that appended fields
        assert cls.VERSION == appended.get(cls.TYPE, 1)


def test_container_defaults_are_not_shared():
    a, b = ScanEvent(scan_id=1, event="start"), ScanEvent(scan_id=2, event="done")
    a.analyzer_deg.append(45.0)
    assert b.analyzer_deg == []
    p, q = Plan(modality="flood", separation_m=0.2), Plan(modality="flood", separation_m=0.3)
    p.curves["q"] = np.zeros(2)
    assert q.curves == {}
    c = Composite(images={}, method="m")
    c.metrics["x"] = 1
    assert Composite(images={}, method="m").metrics == {}


@pytest.mark.parametrize(
    "tag, fields",
    [
        ("flood", ("flood", 0, 0, 0, 0)),
        ("off", ("off", 0, 0, 0, 0)),
        ("stripe:3/30", ("stripe", 3, 30, 0, 0)),
        ("checker:16:8", ("checker", 0, 0, 16, 8)),
        (PatternSpec("checker", size=4, shift=4), ("checker", 0, 0, 4, 4)),
    ],
)
def test_pattern_message_of_a_tag_or_spec(tag, fields):
    m = Pattern.of(tag, scan_id=5, step=2)
    assert (m.kind, m.index, m.count, m.size, m.shift) == fields
    assert (m.scan_id, m.step) == (5, 2)
    assert m.spec() == parse(tag)


@pytest.mark.parametrize(
    "bad, match",
    [("zebra", "'zebra' is not flood, off"), ("stripe:4/4", "index=4 count=4"), ("checker:0:2", "size=0")],
)
def test_pattern_of_a_bad_tag_names_it(bad, match):
    with pytest.raises(PatternError, match=match):
        Pattern.of(bad)


def test_pattern_fields_that_describe_no_pattern_fail_in_spec():
    with pytest.raises(PatternError, match="checker pattern size=0 shift=0"):
        Pattern(kind="checker").spec()
    with pytest.raises(PatternError, match="stripe pattern index=0 count=0"):
        Pattern(kind="stripe").spec()


_specs = st.one_of(
    st.sampled_from([PatternSpec("flood"), PatternSpec("off")]),
    st.integers(1, 1000).flatmap(lambda n: st.builds(PatternSpec, st.just("stripe"), st.integers(0, n - 1),
                                                     st.just(n))),
    st.builds(lambda size, shift: PatternSpec("checker", size=size, shift=shift), st.integers(1, 512),
              st.integers(0, 512)),
)


@given(_specs, st.integers(0, 2**31), st.integers(0, 2**31))
def test_pattern_survives_the_wire_as_the_same_spec(spec, scan_id, step):
    m = Pattern.of(str(spec), scan_id=scan_id, step=step)
    frames = [bytes(memoryview(f).cast("B")) for f in encode(m, topic="/p")]
    back = decode(frames, topic="/p", expect=Pattern)
    assert back.spec() == spec and str(back.spec()) == str(spec)
    assert (back.scan_id, back.step) == (scan_id, step)

