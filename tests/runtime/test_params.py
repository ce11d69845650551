"""Typed node parameters (runtime/params.py): defaults, coercion of strings, validation, one clear line."""

import dataclasses
from typing import Any, Literal

import pytest
from polarstripe.nodes.demo import Talker
from polarstripe.runtime.params import NodeParams, ParamError, ParamSet, build_params, parse_assignments


class _Params(NodeParams):
    mode: Literal["flood", "stripes"] = "flood"
    angles: list[float] = [0.0, 90.0]
    limit: int | None = None
    flag: bool = False
    label: str = "x"


def test_params_are_typed_coerced_and_validated():
    p = build_params(
        _Params, {"mode": "stripes", "angles": "0,45,90", "limit": "none", "heartbeat_s": "2"}
    )
    assert (p.mode, p.angles, p.limit, p.heartbeat_s) == ("stripes", [0.0, 45.0, 90.0], None, 2.0)
    assert build_params(_Params, {"angles": "[1, 2]", "limit": "3"}).limit == 3
    assert build_params(Talker.Params, {}).rate_hz == 10.0
    with pytest.raises(
        ParamError, match="node 'x': param 'mode': bad value 'checker': expected one of flood"
    ):
        build_params(_Params, {"mode": "checker"}, node="x")
    with pytest.raises(ParamError, match="unknown param 'speed'"):
        build_params(Talker.Params, {"speed": 1}, node="x")
    with pytest.raises(ParamError, match="param 'rate_hz': bad value 'fast'"):
        build_params(Talker.Params, {"rate_hz": "fast"}, node="x")
    with pytest.raises(ParamError, match="rate_hz must be > 0, got -1.0"):
        build_params(Talker.Params, {"rate_hz": -1}, node="x")
    with pytest.raises(ParamError, match="param 'count': bad value True"):
        build_params(Talker.Params, {"count": True}, node="x")
    with pytest.raises(ParamError, match="expected KEY=VALUE"):
        parse_assignments(["novalue"])
    assert parse_assignments(["a=b=c"]) == {"a": "b=c"}



class _Options(ParamSet):
    port: str
    table: dict[str, Any] = {"a": 1}


def test_tables_from_toml_or_json_and_required_keys():
    o = build_params(_Options, {"port": "/dev/ttyUSB1", "table": '{"device": "/dev/video2", "width": 640}'})
    assert o.table == {"device": "/dev/video2", "width": 640} and o.port == "/dev/ttyUSB1"
    d1, d2 = build_params(_Options, {"port": "p"}), build_params(_Options, {"port": "p", "table": ""})
    assert d1.table == {"a": 1} and d1.table is not _Options(port="p").table and d2.table == {}
    with pytest.raises(ParamError, match=r"^backend 'b': option 'table': bad value '\[1\]': expected a tab"):
        build_params(_Options, {"port": "p", "table": "[1]"}, what="backend 'b'", noun="option")
    with pytest.raises(ParamError, match=r"^backend 'b': missing option 'port'$"):
        build_params(_Options, {}, what="backend 'b'", noun="option")


def test_each_instance_gets_its_own_list_and_params_are_frozen():
    a, b = build_params(_Params, {}), build_params(_Params, {})
    assert a.angles == [0.0, 90.0] and a.angles is not b.angles
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.mode = "stripes"
    assert a.as_dict()["angles"] == [0.0, 90.0] and a.as_dict()["pub_hwm"] == 100


@pytest.mark.parametrize(("value", "expected"), [
    ("yes", True), ("OFF", False), ("1", True), (True, True), (False, False),
])
def test_bools_from_words(value, expected):
    assert build_params(_Params, {"flag": value}).flag is expected


@pytest.mark.parametrize(("key", "value", "problem"), [
    ("flag", "maybe", "expected a bool"),
    ("flag", 1, "expected a bool"),
    ("limit", 2.5, "expected an int"),
    ("angles", "[1, ", "not a list"),
    ("angles", 3.0, "expected a list"),
    ("label", ["a"], "expected a string"),
    ("mode", "Flood", "expected one of flood, stripes"),
])
def test_bad_values_name_the_param_the_value_and_the_problem(key, value, problem):
    with pytest.raises(ParamError) as info:
        build_params(_Params, {key: value}, node="n")
    assert str(info.value).startswith(f"node 'n': param {key!r}: bad value {value!r}: ") and problem in str(
        info.value)


def test_numbers_and_none_are_coerced_both_ways():
    p = build_params(_Params, {"limit": 4.0, "label": 7, "angles": [1, "2.5"], "heartbeat_s": 0})
    assert (p.limit, p.label, p.angles, p.heartbeat_s) == (4, "7", [1.0, 2.5], 0.0)
    assert build_params(_Params, {"limit": "null"}).limit is None
    assert build_params(_Params, {"angles": ""}).angles == []


@pytest.mark.parametrize(("values", "text"), [
    ({"heartbeat_s": -1}, "heartbeat_s must be >= 0"),
    ({"pub_hwm": 0}, "pub_hwm must be >= 1"),
    ({"max_message_bytes": 0}, "max_message_bytes must be > 0"),
])
def test_the_common_params_are_validated_for_every_node(values, text):
    with pytest.raises(ParamError, match=f"node 'n': params: {text}"):
        build_params(_Params, values, node="n")


def test_assignments_need_a_key():
    with pytest.raises(ParamError, match="arg '=x': expected KEY=VALUE"):
        parse_assignments(["=x"], what="arg")
    assert parse_assignments([" k =v ", "e="]) == {"k": "v ", "e": ""}
