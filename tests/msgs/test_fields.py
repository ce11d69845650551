"""Field kinds (msgs/fields.py) on their own: which annotations are carried, how each kind checks a value on
the way out (``enc``) and in (``dec``), their JSON Schemas. The whole-message paths are in test_codec.py."""

from __future__ import annotations

import math
from typing import Any, Literal, Optional

import jsonschema
import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from polarstripe.msgs.fields import (
    ArrayKind,
    DictKind,
    ListKind,
    OptionalKind,
    exact_type,
    kind_of,
)


def enc(tp, v):
    bufs: list = []
    out = kind_of(tp).enc(v, bufs)
    return out, bufs


def dec(tp, v, bufs=()):
    return kind_of(tp).dec(v, list(bufs))


# ---- which annotations are carried ----------------------------------------------------------------------
@pytest.mark.parametrize(
    "tp, kind",
    [
        (int | None, OptionalKind),
        (Optional[float], OptionalKind),  # noqa: UP045  (the typing.Optional spelling too)
        (None | str, OptionalKind),
        (list[Literal["a", "b"]], ListKind),
        (list[int | None], ListKind),
        (list[int] | None, OptionalKind),
        (dict[str, np.ndarray], DictKind),
        (dict[str, Any], DictKind),
        (np.ndarray | None, OptionalKind),
        (np.ndarray, ArrayKind),
    ],
)
def test_supported_annotations(tp, kind):
    assert isinstance(kind_of(tp), kind)


@pytest.mark.parametrize(
    "tp, match",
    [
        (list[np.ndarray], r"list\[.*ndarray.*\] is not supported"),
        (list[list[int]], r"list\[list\[int\]\] is not supported"),
        (list[dict[str, int]], "is not supported"),
        (dict[str, list[int]], r"dict\[str, list\[int\]\] is not supported"),
        (dict[str, dict[str, int]], "is not supported"),
        (dict[int, str], "unsupported field type"),
        (Literal[1, 2], "unsupported field type"),
        (int | str, "unsupported field type"),
        (int | str | None, "unsupported field type"),
        (set[int], "unsupported field type"),
        (tuple[int, ...], "unsupported field type"),
        (complex, "unsupported field type"),
        (list, "unsupported field type"),
    ],
)
def test_unsupported_annotations_are_type_errors(tp, match):
    with pytest.raises(TypeError, match=match):
        kind_of(tp)


# ---- scalars: what is accepted, converted or refused ----------------------------------------------------
@pytest.mark.parametrize(
    "tp, value, wire",
    [
        (bool, np.bool_(True), True),
        (int, np.int16(-3), -3),
        (int, np.uint64(2**64 - 1), 2**64 - 1),
        (float, 3, 3.0),
        (float, np.float32(0.5), 0.5),
        (float, np.int8(2), 2.0),
        (float, math.inf, math.inf),
        (str, "ü", "ü"),
        (bytes, b"\x00", b"\x00"),
        (Literal["x", "y"], "y", "y"),
        (int | None, None, None),
    ],
)
def test_scalar_encoding_converts_numpy_and_int_to_plain_python(tp, value, wire):
    out, bufs = enc(tp, value)
    assert out == wire and type(out) is type(wire) and bufs == []


@pytest.mark.parametrize(
    "tp, value, match",
    [
        (bool, 1, "expected bool, got int 1"),
        (int, True, "expected int, got bool True"),
        (int, 1.0, "expected int, got float 1.0"),
        (int, "1", "expected int, got str '1'"),
        (float, False, "expected float, got bool False"),
        (float, "0.5", "expected float, got str"),
        (float, np.complex64(1), "expected float, got complex64"),
        (str, b"a", "expected str, got bytes"),
        (bytes, bytearray(b"a"), "expected bytes, got bytearray"),
        (bytes, "a", "expected bytes, got str"),
        (Literal["flood", "off"], "stripe", "expected one of flood, off, got 'stripe'"),
        (Literal["flood", "off"], 1, "expected one of flood, off, got 1"),
        (list[int], 5, "expected a list, got int"),
        (list[int], [1, "2"], "expected int, got str '2'"),
        (dict[str, int], [("a", 1)], "expected a dict, got list"),
        (dict[str, int], {1: 2}, "expected str keys, got int 1"),
        (dict[str, int], {"a": 1.5}, "key 'a': expected int, got float 1.5"),
        (np.ndarray, [1, 2], "expected numpy.ndarray, got list"),
        (np.ndarray, np.array(["a"]), "dtype <U1 cannot travel"),
        (np.ndarray, np.zeros(2, "V4"), "cannot travel"),
        (np.ndarray, np.array([1], object), "dtype object cannot travel"),
    ],
)
def test_encoding_refuses_with_the_problem(tp, value, match):
    with pytest.raises(ValueError, match=match):
        enc(tp, value)


def test_a_long_value_is_cut_in_the_error_text():
    with pytest.raises(ValueError) as info:
        enc(int, "x" * 1000)
    assert len(str(info.value)) < 100


@pytest.mark.parametrize(
    "tp, wire, match",
    [
        (bool, 1, "expected bool"),
        (int, 1.0, "expected int"),
        (list[int], (1, 2), "expected a list, got tuple"),  # the wire has lists only
        (dict[str, int], [1], "expected a map, got list"),
        (dict[str, float], {b"k": 1.0}, "expected str keys, got bytes"),
        (dict[str, float], {"k": "v"}, "key 'k': expected float"),
        (Literal["a"], "b", "expected one of a, got 'b'"),
    ],
)
def test_decoding_refuses_with_the_problem(tp, wire, match):
    with pytest.raises(ValueError, match=match):
        dec(tp, wire)


def test_a_tuple_goes_out_as_a_list():
    assert enc(list[float], (1, 2.5)) == ([1.0, 2.5], [])


# ---- dict[str, Any]: MessagePack primitives only -------------------------------------------------------
def test_any_converts_numpy_scalars_and_tuples():
    out, _ = enc(dict[str, Any], {"n": np.int32(3), "f": np.float32(0.5), "b": np.bool_(False),
                                  "t": (1, (2, None))})
    assert out == {"n": 3, "f": 0.5, "b": False, "t": [1, [2, None]]}
    assert [type(out[k]) for k in ("n", "f", "b")] == [int, float, bool]
    assert msgpack.unpackb(msgpack.packb(out)) == out  # nothing numpy left for the packer


@pytest.mark.parametrize(
    "value, match",
    [
        ({1, 2}, "set is not a MessagePack primitive"),
        (np.zeros(2), "ndarray is not a MessagePack primitive"),
        (b"raw", "bytes is not a MessagePack primitive"),
        ({"a": {2: "x"}}, "expected str keys, got int 2"),
    ],
)
def test_any_refuses_what_is_not_a_primitive(value, match):
    with pytest.raises(ValueError, match=match):
        enc(Any, value)


def test_any_nesting_is_limited():
    deep: Any = 1
    for _ in range(8):
        deep = [deep]
    assert enc(Any, deep)[0] == deep  # 8 levels of lists: fine
    with pytest.raises(ValueError, match="nested deeper than 8 levels"):
        enc(Any, [deep])


_prim = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3),
    max_leaves=10,
)


@given(_prim)
def test_any_round_trips_primitives_unchanged(v):
    out, _ = enc(Any, v)
    assert out == v
    assert dec(Any, out) == v


_ints = st.integers(-(2**63), 2**64 - 1)


@given(st.none() | st.lists(_ints, max_size=4), st.dictionaries(st.text(max_size=4), st.floats(), max_size=4))
def test_containers_round_trip(ints, floats):
    out, _ = enc(list[int] | None, ints)
    assert dec(list[int] | None, out) == ints
    out, _ = enc(dict[str, float], floats)
    back = dec(dict[str, float], out)
    assert back.keys() == floats.keys()
    assert all(back[k] == v or (math.isnan(v) and math.isnan(back[k])) for k, v in floats.items())


# ---- arrays ---------------------------------------------------------------------------------------------
def test_array_descriptor_and_buffer():
    a = np.arange(12, dtype=">i4").reshape(3, 4)[:, ::2]  # big-endian, not contiguous
    out, bufs = enc(np.ndarray, a)
    assert out == [0, ">i4", (3, 2)]
    assert len(bufs) == 1 and bufs[0].flags.c_contiguous and bufs[0].tolist() == a.tolist()
    back = dec(np.ndarray, [0, ">i4", [3, 2]], [memoryview(bufs[0].tobytes())])
    assert back.dtype == np.dtype(">i4") and back.tolist() == a.tolist() and not back.flags.writeable


def test_arrays_number_their_buffers_in_order():
    bufs: list = []
    k = kind_of(dict[str, np.ndarray])
    out = k.enc({"a": np.zeros(1, np.uint8), "b": np.ones(2, np.uint8)}, bufs)
    assert out == {"a": [0, "|u1", (1,)], "b": [1, "|u1", (2,)]} and len(bufs) == 2


def test_zero_dimensional_and_empty_arrays_decode():
    scalar = dec(np.ndarray, [0, "<f8", []], [memoryview(np.float64(2.5).tobytes())])
    assert scalar.shape == () and scalar[()] == 2.5
    empty = dec(np.ndarray, [0, "<u2", [0, 5]], [memoryview(b"")])
    assert empty.shape == (0, 5)


@pytest.mark.parametrize(
    "wire, nbytes, match",
    [
        ([0, "<U4", [1]], 16, "bad dtype '<U4'"),
        ([0, "|O", [1]], 8, "bad dtype"),
        ([0, 5, [1]], 8, "bad dtype 5"),
        ([0, "nonsense", [1]], 8, "bad dtype"),
        ([0, "<u2", [True, 2]], 4, "bad shape"),
        ([0, "<u2", [2.0]], 4, "bad shape"),
        ([0, "<u2", "2"], 4, "bad shape"),
        ([True, "<u2", [2]], 4, "buffer index True out of range"),
        ([-1, "<u2", [2]], 4, "out of range"),
        ([0, "<u2"], 4, r"expected an array descriptor \[buf, dtype, shape\]"),
        ([0, "<u2", [3]], 4, "needs 6 bytes, buffer has 4"),
    ],
)
def test_bad_array_descriptors(wire, nbytes, match):
    with pytest.raises(ValueError, match=match):
        dec(np.ndarray, wire, [memoryview(bytes(nbytes))])


def test_a_buffer_is_taken_once():
    bufs = [memoryview(bytes(4))]
    kind_of(np.ndarray).dec([0, "<u2", [2]], bufs)
    assert bufs == [None]  # taken: what is left over are stray frames
    with pytest.raises(ValueError, match="buffer 0 is taken by another array"):
        kind_of(np.ndarray).dec([0, "<u2", [2]], bufs)


@given(
    st.sampled_from(["<u2", "|u1", "<i8", ">f4", "<c16", "|b1"]),
    st.lists(st.integers(0, 4), max_size=3),
)
def test_arrays_round_trip_through_descriptor_and_bytes(dtype, shape):
    a = (np.arange(int(np.prod(shape)), dtype=np.int64) % 7).astype(dtype).reshape(shape)
    out, bufs = enc(np.ndarray, a)
    back = dec(np.ndarray, [out[0], out[1], list(out[2])], [memoryview(b.tobytes()) for b in bufs])
    assert back.dtype == a.dtype and back.shape == a.shape and np.array_equal(back, a)


# ---- the decoder's fast path and the JSON Schemas --------------------------------------------------------
def test_exact_types_for_the_fast_path():
    assert [exact_type(kind_of(t)) for t in (bool, int, float, str, bytes)] == [bool, int, float, str, bytes]
    assert exact_type(kind_of(float | None)) is type(None)
    never = exact_type(kind_of(list[int]))
    assert never not in (list, int, type(None)) and exact_type(kind_of(np.ndarray)) is never
    assert exact_type(kind_of(Literal["a"])) is never  # a literal must always be checked


@pytest.mark.parametrize(
    "tp, good, bad",
    [
        (int | None, [None, 3], [1.5, "3"]),
        (Literal["a", "b"], ["a"], ["c", 1]),
        (list[float], [[], [1, 2.5]], [[1, "x"], {}]),
        (dict[str, bool], [{}, {"k": True}], [{"k": 1}, []]),
        (bytes, ["AAE="], [3]),
        (np.ndarray, [{"dtype": "<u2", "shape": [2], "data": "AAAAAA=="}],
         [{"dtype": "<u2", "shape": [-1], "data": ""}, {"dtype": "<u2", "shape": [2]}]),
        (Any, [None, 1, "x", [1, {"a": None}]], []),
    ],
)
def test_kind_schemas_accept_and_refuse(tp, good, bad):
    schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", **kind_of(tp).schema()}
    jsonschema.Draft202012Validator.check_schema(schema)
    v = jsonschema.Draft202012Validator(schema)
    for x in good:
        assert v.is_valid(x), x
    for x in bad:
        assert not v.is_valid(x), x
