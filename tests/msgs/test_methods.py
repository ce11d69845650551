"""The imaging methods: family, polarization, the patterns of a pass, which frames a scan accepts."""

import pytest
from polarstripe.msgs import METHOD_NAMES, Method


def test_the_table():
    assert METHOD_NAMES == ("flood", "polarized_flood", "stripes", "polarized_stripes", "hf_separation")
    assert [m.polarized for m in Method] == [False, True, False, True, False]
    assert [m.family for m in Method] == ["flood", "flood", "stripe", "stripe", "checker"]


def test_patterns_of_a_pass():
    stripes = [str(p) for p in Method.POLARIZED_STRIPES.patterns(3, 16)]
    assert stripes == ["stripe:0/3", "stripe:1/3", "stripe:2/3"]
    assert [str(p) for p in Method.HF_SEPARATION.patterns(3, 16)] == ["checker:16:0", "checker:16:16"]
    assert [str(p) for p in Method.FLOOD.patterns(3, 16)] == ["flood"]


def test_accepts_only_its_family():
    assert Method.STRIPES.accepts("stripe:2/30")
    assert not Method.STRIPES.accepts("flood")
    assert not Method.HF_SEPARATION.accepts("stripe:1/2")
    assert not Method.FLOOD.accepts("stripe:x")


def test_unknown_method_names_the_choices():
    with pytest.raises(ValueError, match="'laser' is not one of flood, polarized_flood"):
        Method.parse("laser")
    assert Method.parse("stripes") is Method.STRIPES and Method.STRIPES == "stripes"


def test_striped_methods_and_lookup():
    assert [m.striped for m in Method] == [False, False, True, True, False]
    assert Method.lookup("polarized_stripes") is Method.POLARIZED_STRIPES
    assert Method.lookup("laser") is None and Method.lookup("") is None
