"""Declaring message types (msgs/base.py): what ``@message`` builds, the fast keyword-only ``__init__``, the
registry's rules, and MessageError's text. The codec's side is in test_codec.py."""

from __future__ import annotations

import dataclasses
from dataclasses import field

import pytest
from hypothesis import given
from hypothesis import strategies as st
from polarstripe.errors import PolarstripeError
from polarstripe.msgs import REGISTRY, Header, Message, MessageError, decode, encode, message
from polarstripe.msgs.fields import exact_type


@message("test_base_sample", version=3)
class Sample(Message):
    """A message with every kind of default."""

    name: str
    count: int = 7
    ratio: float | None = None
    tags: list[str] = field(default_factory=list)
    extra: dict[str, int] = field(default_factory=dict)


@message("test_base_checked")
class Checked(Message):
    """A type with its own __post_init__: the dataclass __init__ is kept so the check runs."""

    low: int
    high: int

    def __post_init__(self):
        if self.low > self.high:
            raise ValueError(f"low {self.low} > high {self.high}")


def test_class_attributes_are_set_from_the_declaration():
    assert (Sample.TYPE, Sample.VERSION) == ("test_base_sample", 3)
    assert [name for name, _ in Sample.FIELDS] == ["name", "count", "ratio", "tags", "extra"]
    assert Sample.FIELD_NAMES == frozenset({"name", "count", "ratio", "tags", "extra"})  # no header
    assert [(n, t) for n, _, t in Sample.FAST_FIELDS] == [
        (n, exact_type(k)) for n, k in Sample.FIELDS
    ]
    assert dict((n, t) for n, _, t in Sample.FAST_FIELDS)["name"] is str
    assert dict((n, t) for n, _, t in Sample.FAST_FIELDS)["ratio"] is type(None)
    assert REGISTRY["test_base_sample"] is Sample


def test_version_is_stored_as_an_int():
    @message("test_base_version_text", version="2")  # type: ignore[arg-type]
    class V(Message):
        x: int

    assert V.VERSION == 2 and type(V.VERSION) is int


def test_fast_init_is_keyword_only_and_applies_defaults():
    s = Sample(name="a")
    assert (s.name, s.count, s.ratio, s.tags, s.extra) == ("a", 7, None, [], {})
    assert s.header == Header()
    with pytest.raises(TypeError):
        Sample("a")  # type: ignore[misc]
    with pytest.raises(TypeError, match="name"):
        Sample()  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="colour"):
        Sample(name="a", colour="red")  # type: ignore[call-arg]
    assert Sample.__init__.__qualname__ == "Sample.__init__"


def test_container_defaults_are_fresh_for_every_instance():
    a, b = Sample(name="a"), Sample(name="b")
    a.tags.append("x")
    a.extra["k"] = 1
    assert b.tags == [] and b.extra == {}
    given_list = ["t"]
    assert Sample(name="c", tags=given_list).tags is given_list  # a given value is taken as is


def test_messages_are_frozen_and_compare_by_value():
    s = Sample(name="a", tags=["x"], header=Header(seq=3))
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.name = "b"  # type: ignore[misc]
    assert s == Sample(name="a", tags=["x"], header=Header(seq=3))
    assert s != Sample(name="a", tags=["x"], header=Header(seq=4))
    assert dataclasses.replace(s, count=9).count == 9 and s.count == 7


def test_header_is_frozen_with_slots():
    h = Header(stamp_ns=1, seq=2, frame_id="cam")
    with pytest.raises(dataclasses.FrozenInstanceError):
        h.seq = 3  # type: ignore[misc]
    assert not hasattr(h, "__dict__")


def test_a_post_init_keeps_the_dataclass_init_and_runs():
    assert Checked(low=1, high=2).high == 2
    with pytest.raises(ValueError, match="low 3 > high 2"):
        Checked(low=3, high=2)


def test_fields_of_a_base_message_come_first():
    @message("test_base_derived")
    class Derived(Sample):
        more: bool = False

    assert [n for n, _ in Derived.FIELDS] == ["name", "count", "ratio", "tags", "extra", "more"]
    d = Derived(name="x", more=True, header=Header(stamp_ns=5))
    assert (d.count, d.more, d.tags) == (7, True, [])
    back = decode([bytes(memoryview(f).cast("B")) for f in encode(d)], expect=Derived)
    assert back == d


def test_only_message_subclasses_can_be_declared():
    with pytest.raises(TypeError, match=r"@message\('test_base_plain'\) needs a subclass of Message"):

        @message("test_base_plain")
        class Plain:
            x: int


def test_redeclaring_the_same_class_is_allowed_another_is_not():
    def declare():
        @message("test_base_again")
        class Again(Message):
            x: int

        return Again

    first, second = declare(), declare()  # same module and qualname: a reload, not a clash
    assert REGISTRY["test_base_again"] is second and first is not second
    with pytest.raises(TypeError, match=r"'test_base_again' is already declared by .*\.Again"):

        @message("test_base_again")
        class Other(Message):
            x: int


@pytest.mark.parametrize(
    "annotation, needle",
    [("set[int]", "Bad.when"), ("list[list[int]]", r"list\[list\[int\]\] is not supported"),
     ("tuple[int, int]", "unsupported field type")],
)
def test_an_unsupported_field_names_the_class_field_and_what_is_allowed(annotation, needle):
    ns: dict = {}
    src = f"class Bad(Message):\n    when: {annotation}\n"
    exec(src, {"Message": Message}, ns)  # noqa: S102
    with pytest.raises(TypeError, match=needle) as info:
        message("test_base_bad_" + str(abs(hash(annotation))))(ns["Bad"])
    assert "allowed: bool, int, float, str, bytes" in str(info.value)


def test_message_error_text_attributes_and_classes():
    e = MessageError("/rig/x", "image", "expected numpy.ndarray, got list")
    assert str(e) == "topic '/rig/x': field 'image': expected numpy.ndarray, got list"
    assert (e.topic, e.field, e.problem) == ("/rig/x", "image", "expected numpy.ndarray, got list")
    assert isinstance(e, PolarstripeError) and isinstance(e, ValueError)


@given(
    name=st.text(max_size=10),
    count=st.none() | st.integers(),
    ratio=st.none() | st.floats(allow_nan=False),
    tags=st.none() | st.lists(st.text(max_size=3), max_size=3),
)
def test_fast_init_gives_what_the_dataclass_init_would(name, count, ratio, tags):
    kw = {"name": name, "ratio": ratio}
    if count is not None:
        kw["count"] = count
    if tags is not None:
        kw["tags"] = tags
    fast = Sample(**kw)
    expected = {"header": Header(), "count": 7, "tags": [], "extra": {}, **kw}
    assert {f.name: getattr(fast, f.name) for f in dataclasses.fields(Sample)} == expected
    assert dataclasses.asdict(fast) == {**expected, "header": dataclasses.asdict(Header())}

