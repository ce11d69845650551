"""The pattern grammar: parse, format, iterate, and one clear error for every bad spec."""

import pytest
from hypothesis import given
from hypothesis import strategies as st
from polarstripe.msgs import Pattern, PatternError, PatternSpec
from polarstripe.msgs.patterns import checker_pair, following, parse, stripe_columns, stripes


@pytest.mark.parametrize("text, spec", [
    ("flood", PatternSpec("flood")),
    ("off", PatternSpec("off")),
    (" Stripe:3/30 ", PatternSpec("stripe", index=3, count=30)),
    ("checker:16:8", PatternSpec("checker", size=16, shift=8)),
    ("gray:3:col:0", PatternSpec("gray", index=3, axis="col")),
    ("gray:0:row:1", PatternSpec("gray", index=0, axis="row", inverse=True)),
])
def test_parse_known_forms(text, spec):
    assert parse(text) == spec
    assert parse(str(spec)) == spec


@pytest.mark.parametrize("text, match", [
    ("stripe:3/3", "index=3 count=3"),
    ("stripe:0/0", "count=0"),
    ("checker:0:0", "size=0"),
    ("gray:3", r"not flood, off, stripe:K/N\[:xSHEETS\], checker:SIZE:SHIFT or gray"),
    ("gray:3:diag:0", "not flood"),
    ("gray:31:col:0", "bit=31"),
    ("stripe:-1/3", "not flood"),
])
def test_bad_specs_name_what_is_wrong(text, match):
    with pytest.raises(PatternError, match=match):
        parse(text)


def test_pattern_error_is_a_value_error():
    with pytest.raises(ValueError):
        parse("nonsense")


@given(st.integers(1, 500).flatmap(lambda n: st.tuples(st.integers(0, n - 1), st.just(n))))
def test_stripe_roundtrip(kn):
    k, n = kn
    assert parse(f"stripe:{k}/{n}") == PatternSpec("stripe", index=k, count=n)
    assert str(parse(f"stripe:{k}/{n}")) == f"stripe:{k}/{n}"


@given(st.integers(1, 300), st.integers(1, 4000))
def test_stripes_tile_the_pattern_without_gap_or_overlap(n, width):
    cols = [stripe_columns(p, width) for p in stripes(n)]
    assert cols[0][0] == 0 and cols[-1][1] == width
    assert all(a[1] == b[0] for a, b in zip(cols, cols[1:], strict=False))


def test_message_roundtrip_and_checker_pair():
    msg = Pattern.of("stripe:4/30", scan_id=7, step=4)
    assert (msg.kind, msg.index, msg.count, msg.scan_id, msg.step) == ("stripe", 4, 30, 7, 4)
    assert msg.spec() == PatternSpec("stripe", 4, 30)
    assert [str(p) for p in checker_pair(16)] == ["checker:16:0", "checker:16:16"]
    with pytest.raises(PatternError, match="no kind"):
        parse(object())
    with pytest.raises(PatternError):
        Pattern(kind="stripe", index=5, count=2).spec()


@pytest.mark.parametrize("tag, nxt", [
    ("stripe:0/3", "stripe:1/3"), ("stripe:2/3", None), ("checker:8:0", "checker:8:8"), ("checker:8:8", None),
    ("flood", None), ("garbage", None),
])
def test_following_pattern_of_a_scan(tag, nxt):
    assert following(tag) == nxt
