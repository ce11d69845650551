"""JSON Schemas of message types (msgs/schema.py): a known answer, what they refuse, and the errors.
(test_codec.py checks that every packed message validates.)"""

from __future__ import annotations

import base64

import jsonschema
import msgpack
import numpy as np
import pytest
from polarstripe.msgs import (
    ALL_TYPES,
    REGISTRY,
    Frame,
    Header,
    Message,
    PolarizerCommand,
    json_schema,
    message,
    pack,
)


@message("test_schema_doc")
class Documented(Message):
    """First paragraph, on
    two lines.

    Second paragraph: not in the description."""

    n: int


def _doc(msg) -> dict:
    """The packed form as a JSON viewer shows it (bin as base64)."""

    def j(v):
        if isinstance(v, bytes):
            return base64.b64encode(v).decode()
        if isinstance(v, dict):
            return {k: j(x) for k, x in v.items()}
        if isinstance(v, list):
            return [j(x) for x in v]
        return v

    return j(msgpack.unpackb(pack(msg), raw=False))


def test_known_schema_of_a_small_type():
    assert json_schema(PolarizerCommand) == {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "polarstripe/polarizer_command",
        "description": "Turn the analyzer to ``target_deg`` [deg].",
        "type": "object",
        "properties": {
            "type": {"const": "polarizer_command"},
            "version": {"const": 1},
            "stamp_ns": {"type": "integer"},
            "seq": {"type": "integer"},
            "frame_id": {"type": "string"},
            "fields": {
                "type": "object",
                "properties": {"target_deg": {"type": "number"}},
                "required": ["target_deg"],
                "additionalProperties": False,
            },
        },
        "required": ["type", "version", "stamp_ns", "seq", "frame_id", "fields"],
        "additionalProperties": False,
    }


def test_description_is_the_first_paragraph_of_the_docstring():
    assert json_schema(Documented)["description"] == "First paragraph, on\n    two lines."


@pytest.mark.parametrize("cls", sorted(REGISTRY.values(), key=lambda c: c.TYPE), ids=lambda c: c.TYPE)
def test_every_registered_schema_is_a_valid_schema_listing_fields_in_order(cls):
    s = json_schema(cls)
    jsonschema.Draft202012Validator.check_schema(s)
    assert s["properties"]["fields"]["required"] == [name for name, _ in cls.FIELDS]
    assert s["title"] == f"polarstripe/{cls.TYPE}" and s["properties"]["version"] == {"const": cls.VERSION}


_frame = Frame(image=np.zeros((2, 3), np.uint16), exposure_s=0.01, header=Header(stamp_ns=1))


def _broken(**changes):
    d = _doc(_frame)
    for path, value in changes.items():
        where, key = (d["fields"], path[2:]) if path.startswith("f_") else (d, path)
        if value is None:
            del where[key]
        else:
            where[key] = value
    return d


@pytest.mark.parametrize(
    "doc",
    [
        _broken(type="log"),
        _broken(version=3),
        _broken(seq=None),
        _broken(extra=1),
        _broken(f_gain=None),
        _broken(f_colour="red"),
        _broken(f_bit_depth=12.5),
        _broken(f_polarizer_deg="north"),
        _broken(f_image={"dtype": "<u2", "shape": [2, 3]}),
        _broken(f_image={"dtype": "<u2", "shape": [-2, 3], "data": ""}),
    ],
    ids=["type", "version", "no-seq", "extra-key", "no-field", "unknown-field", "int", "optional",
         "array-no-data", "negative-shape"],
)
def test_the_schema_refuses_what_unpack_would(doc):
    validator = jsonschema.Draft202012Validator(json_schema(Frame))
    assert validator.is_valid(_doc(_frame))
    assert not validator.is_valid(doc)


def test_literal_fields_are_enums():
    from polarstripe.msgs import Log

    s = json_schema(Log)["properties"]["fields"]["properties"]["level"]
    assert s == {"enum": ["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"]}


@pytest.mark.parametrize("bad", [Message, int, Frame(image=np.zeros(1), exposure_s=0.0), "frame", None])
def test_only_declared_message_types_have_a_schema(bad):
    with pytest.raises(TypeError, match="is not a declared message type"):
        json_schema(bad)


def test_all_types_have_distinct_titles():
    titles = [json_schema(c)["title"] for c in ALL_TYPES]
    assert len(set(titles)) == len(titles)
