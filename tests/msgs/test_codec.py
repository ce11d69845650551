import base64
import dataclasses
import types
import typing
from typing import Any, Literal

import jsonschema
import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from polarstripe.msgs import (
    ALL_TYPES,
    Composite,
    Frame,
    Header,
    Log,
    Message,
    MessageError,
    Plan,
    PolarizerCommand,
    decode,
    describe,
    encode,
    json_schema,
    message,
    pack,
    unpack,
)

# ---- strategies written from the annotations, independently of the codec's own kind table ---------------
_text = st.text(max_size=20)
_prim = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats(allow_nan=False) | _text,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(_text, inner, max_size=3),
    max_leaves=8,
)
_dtypes = st.sampled_from(["<u2", "<u1", "<i4", "<f4", "<f8", "|b1", "<c8", ">i2"])


def _arrays():
    return _dtypes.flatmap(
        lambda dt: hnp.arrays(np.dtype(dt), hnp.array_shapes(min_dims=0, max_dims=3, max_side=5))
    )


def _strategy(tp):
    if tp is bool:
        return st.booleans()
    if tp is int:
        return st.integers(-(2**63), 2**63 - 1)
    if tp is float:
        return st.floats(allow_nan=False)
    if tp is str:
        return _text
    if tp is np.ndarray:
        return _arrays()
    if tp is Any:
        return _prim
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        return st.sampled_from(args)
    if origin in (typing.Union, types.UnionType):
        return st.none() | _strategy(next(a for a in args if a is not type(None)))
    if origin is list:
        return st.lists(_strategy(args[0]), max_size=4)
    if origin is dict:
        return st.dictionaries(_text, _strategy(args[1]), max_size=3)
    raise AssertionError(f"no strategy for {tp}")


def _messages(cls):
    hints = typing.get_type_hints(cls)
    fields = {f.name: _strategy(hints[f.name]) for f in dataclasses.fields(cls) if f.name != "header"}
    header = st.builds(Header, st.integers(1, 2**63 - 1), st.integers(0, 2**63 - 1), _text)
    return st.builds(cls, header=header, **fields)


def _same(a, b):
    """Deep equality where arrays must match in dtype, shape and every byte."""
    if isinstance(a, np.ndarray):
        return (
            isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.tobytes() == b.tobytes()
        )
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return (
            isinstance(b, list) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
        )
    if isinstance(a, float):
        return type(b) is float and (a == b)
    return type(a) is type(b) and a == b


def _assert_roundtrip(msg, back):
    assert type(back) is type(msg)
    assert back.header == msg.header
    for f in dataclasses.fields(msg):
        assert _same(getattr(msg, f.name), getattr(back, f.name)), f.name


def _as_frames(msg):
    return [
        bytes(memoryview(f).cast("B")) if not isinstance(f, bytes) else f for f in encode(msg, topic="/t")
    ]


@pytest.mark.parametrize("cls", ALL_TYPES, ids=lambda c: c.TYPE)
@settings(max_examples=25, deadline=None)
@given(data=st.data())
def test_every_type_round_trips_through_frames_and_packed_form(cls, data):
    msg = data.draw(_messages(cls))
    _assert_roundtrip(msg, decode(_as_frames(msg), topic="/t", expect=cls))
    _assert_roundtrip(msg, unpack(pack(msg), expect=cls))


@pytest.mark.parametrize("cls", ALL_TYPES, ids=lambda c: c.TYPE)
@settings(max_examples=10, deadline=None)
@given(data=st.data())
def test_packed_form_matches_the_json_schema(cls, data):
    msg = data.draw(_messages(cls))
    doc = msgpack.unpackb(pack(msg), raw=False)

    def jsonable(v):
        if isinstance(v, bytes):
            return base64.b64encode(v).decode()
        if isinstance(v, dict):
            return {k: jsonable(x) for k, x in v.items()}
        if isinstance(v, list):
            return [jsonable(x) for x in v]
        return v

    jsonschema.Draft202012Validator(json_schema(cls)).validate(jsonable(doc))


def test_arrays_arrive_as_read_only_views_of_the_received_buffer():
    img = np.arange(1024 * 1280, dtype=np.uint16).reshape(1024, 1280)
    header, buf = encode(Frame(image=img, exposure_s=0.01), topic="/t")
    received = bytearray(memoryview(buf).cast("B"))  # a writable receive buffer, like a zmq frame
    back = decode([header, received], topic="/t", expect=Frame)
    assert np.shares_memory(back.image, np.frombuffer(received, np.uint8))
    assert not back.image.flags.writeable
    with pytest.raises(ValueError):
        back.image[0, 0] = 1
    assert back.image[1023, 1279] == (1024 * 1280 - 1) % 65536


def test_non_contiguous_array_is_sent_in_c_order():
    a = np.arange(20, dtype=np.int32).reshape(4, 5)[:, ::2]
    back = decode(_as_frames(Composite(images={"a": a}, method="m")), expect=Composite)
    assert back.images["a"].tolist() == [[0, 2, 4], [5, 7, 9], [10, 12, 14], [15, 17, 19]]


def test_publisher_stamps_seq_and_keeps_a_given_stamp():
    m = PolarizerCommand(target_deg=45.0, header=Header(stamp_ns=123, seq=9, frame_id="stage"))
    back = decode(encode(m, seq=4), expect=PolarizerCommand)
    assert back.header == Header(stamp_ns=123, seq=4, frame_id="stage")
    fresh = decode(encode(PolarizerCommand(target_deg=1.0)), expect=PolarizerCommand)
    assert fresh.header.stamp_ns > 1_600_000_000 * 10**9


# ---- every kind of bad message: one error class naming topic and field ------------------------------
def _head(msg, *, append=(), **changes):
    """The frames of ``msg`` with header items or fields (``fields.NAME``; ``_DROP`` removes it) replaced."""
    frames = encode(msg, topic="/t")
    head = msgpack.unpackb(frames[0], raw=False)
    assert isinstance(head, list)  # [type, version, stamp_ns, seq, frame_id, *values in declared order]
    names = ["type", "version", "stamp_ns", "seq", "frame_id", *(name for name, _ in type(msg).FIELDS)]
    for k, v in changes.items():
        i = names.index(k.removeprefix("fields."))
        head[i] = v
    head = [v for v in head if v is not _DROP] + list(append)
    return [msgpack.packb(head, use_bin_type=True), *[np.ascontiguousarray(b).tobytes() for b in frames[1:]]]


_DROP = object()


def _desc(buf, dtype, shape):
    return [buf, dtype, shape]


_frame = Frame(image=np.zeros((4, 6), np.uint16), exposure_s=0.01)


@pytest.mark.parametrize(
    ("frames", "field", "problem"),
    [
        ([b"\xc1\xff garbage"], "header", "not a MessagePack header"),
        ([msgpack.packb({"type": "frame"})], "header", "expected an array, got dict"),
        ([msgpack.packb([1, 2, 3])], "header", r"expected \[type, .*, frame_id, \*fields\], got 3 items"),
        ([], "header", "empty message"),
        (_head(_frame, type="nonesuch"), "type", "unknown message type 'nonesuch'"),
        (_head(Log(level="INFO", node="a", text="b")), "type", "expected 'frame', got 'log'"),
        (_head(_frame, version=7), "version", "unknown schema version 7"),
        (_head(_frame, **{"fields.mosaic_deg": _DROP}), "mosaic_deg", "missing"),
        (_head(_frame, **{"fields.step": _DROP, "fields.mosaic_deg": _DROP}), "step", "missing"),
        (_head(_frame, **{"fields.exposure_s": "fast"}), "exposure_s", "expected float"),
        (_head(_frame, **{"fields.bit_depth": 1.5}), "bit_depth", "expected int"),
        (_head(_frame, append=["red"]), "fields", "10 values but 'frame' has 9 fields"),
        (_head(_frame, **{"fields.image": {"buf": 0, "dtype": "<u2", "shape": [4, 6]}}), "image",
         r"expected an array descriptor \[buf, dtype, shape\]"),
        (_head(_frame, **{"fields.image": _desc(0, "<u2", [5, 6])}), "image", "needs 60 bytes"),
        (_head(_frame, **{"fields.image": _desc(0, "<f8", [4, 6])}), "image", "needs 192 bytes"),
        (_head(_frame, **{"fields.image": _desc(0, "|O", [4, 6])}), "image", "bad dtype"),
        (_head(_frame, **{"fields.image": _desc(3, "<u2", [4, 6])}), "image", "out of range"),
        (_head(_frame, **{"fields.image": _desc(0, "<u2", [-4, 6])}), "image", "bad shape"),
        (_head(_frame) + [b"stray"], "buffers", "2 buffer frames but 1 used"),
        (_head(_frame, seq="x"), "seq", "expected int"),
        (_head(_frame, frame_id=3), "frame_id", "expected str"),
    ],
)
def test_bad_messages_raise_one_error_naming_topic_and_field(frames, field, problem):
    with pytest.raises(MessageError, match=problem) as info:
        decode(frames, topic="/rig/camera/frame", expect=Frame)
    assert info.value.topic == "/rig/camera/frame"
    assert info.value.field == field
    assert str(info.value).startswith(f"topic '/rig/camera/frame': field '{field}': ")


def test_size_limit():
    frames = _as_frames(Frame(image=np.zeros(1000, np.uint8), exposure_s=0.1))
    assert decode(frames, max_bytes=2000, expect=Frame).image.size == 1000
    with pytest.raises(MessageError, match="exceeds the limit of 999 bytes") as info:
        decode(frames, topic="/t", max_bytes=999)
    assert info.value.field == "size"
    with pytest.raises(MessageError, match="exceeds"):
        unpack(pack(Frame(image=np.zeros(1000, np.uint8), exposure_s=0.1)), max_bytes=999)


@pytest.mark.parametrize(
    ("msg", "field"),
    [
        (Frame(image=[[1, 2]], exposure_s=0.1), "image"),
        (Frame(image=np.array(["a"], dtype=object), exposure_s=0.1), "image"),
        (Log(level="LOUD", node="a", text="b"), "level"),
        (Composite(images={}, method="m", metrics={"f": object()}), "metrics"),
        (Composite(images={}, method="m", metrics={1: 2}), "metrics"),
        (Plan(modality="stripes", separation_m="far"), "separation_m"),
        (PolarizerCommand(target_deg=True), "target_deg"),
    ],
)
def test_encoding_refuses_values_that_do_not_match_the_declared_type(msg, field):
    with pytest.raises(MessageError) as info:
        encode(msg, topic="/t")
    assert info.value.field == field


def test_declaring_an_unsupported_field_type_fails_at_once():
    with pytest.raises(TypeError, match="Bad.when"):

        @message("test_bad_type")
        class Bad(Message):
            when: set[int]


def test_a_type_name_cannot_be_declared_twice():
    with pytest.raises(TypeError, match="already declared"):

        @message("frame")
        class Frame2(Message):
            x: int


def test_describe_summarises_arrays_without_the_class():
    msg = Composite(images={"max": np.zeros((3, 4), np.uint16)}, method="stripes", metrics={"contrast": 0.5})
    d = describe(_as_frames(msg), topic="/t")
    assert (d["type"], d["version"]) == ("composite", 1)
    assert d["fields"] == {
        "images": {"max": "array <u2[3, 4]"},
        "method": "stripes",
        "scan_id": 0,
        "metrics": {"contrast": 0.5},
    }
    with pytest.raises(MessageError, match="field 'header'"):
        describe([b"\xc1"], topic="/t")


def _packed(msg, **changes):
    doc = msgpack.unpackb(pack(msg), raw=False)
    for k, v in changes.items():
        where, key = (doc["fields"], k.removeprefix("fields.")) if k.startswith("fields.") else (doc, k)
        if v is _DROP:
            del where[key]
        else:
            where[key] = v
    return msgpack.packb(doc, use_bin_type=True)


@pytest.mark.parametrize(
    ("blob", "field", "problem"),
    [
        (_packed(_frame, **{"fields.color": "red"}), "color", "unknown field of 'frame'"),
        (_packed(_frame, **{"fields.gain": _DROP}), "gain", "missing"),
        (_packed(_frame, extra=1), "extra", "unknown header key"),
        (_packed(_frame, seq=_DROP), "seq", "missing from the header"),
        (_packed(_frame, **{"fields.image": {"dtype": "<u2", "shape": [5, 6], "data": b"12"}}), "image",
         "needs 60 bytes, buffer has 2"),
        (msgpack.packb([1]), "header", "expected a map"),
    ],
)
def test_bad_packed_messages_raise_one_error_naming_the_field(blob, field, problem):
    with pytest.raises(MessageError, match=problem) as info:
        unpack(blob, topic="/t", expect=Frame)
    assert info.value.field == field


def test_describe_shows_an_unknown_type_by_position():
    head = ["nonesuch", 1, 5, 0, "", 42, [0, "<u2", [2, 3]]]
    d = describe([msgpack.packb(head), bytes(12)], topic="/t")
    assert (d["type"], d["stamp_ns"], d["fields"]) == ("nonesuch", 5, {"#0": 42, "#1": [0, "<u2", [2, 3]]})


def test_an_array_frame_cannot_be_taken_twice():
    two = Composite(images={"a": np.zeros(4, np.uint16), "b": np.ones(4, np.uint16)}, method="m")
    frames = _head(two, **{"fields.images": {"a": _desc(0, "<u2", [4]), "b": _desc(0, "<u2", [4])}})
    with pytest.raises(MessageError, match="buffer 0 is taken by another array") as info:
        decode(frames, topic="/t", expect=Composite)
    assert info.value.field == "images"
