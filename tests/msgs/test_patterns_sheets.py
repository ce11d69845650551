"""Several sheets per frame: ``stripe:I/N:xK`` (msgs/patterns.py) — the positions each frame lights, a scan
of ⌈N/K⌉ frames lighting every position exactly once, the tag, and the messages that carry it (their
versions: an older reader gets the old meaning or a clear error)."""

import math

import msgpack
import pytest
from hypothesis import given
from hypothesis import strategies as st
from polarstripe.msgs import Method, Pattern, PatternError, PatternSpec, ScanEvent, decode, encode
from polarstripe.msgs.patterns import (
    following,
    parse,
    sheet_columns,
    sheet_positions,
    single_sheets,
    stripe_columns,
    stripes,
)


def test_three_sheets_of_thirty_are_ten_stripes_apart():
    p = parse("stripe:3/30:x3")
    assert p == PatternSpec("stripe", index=3, count=30, sheets=3) and str(p) == "stripe:3/30:x3"
    assert sheet_positions(p) == (3, 13, 23)
    assert sheet_columns(p, 1024) == [(102, 136), (443, 477), (785, 819)]    # floor(k·1024/30)
    assert following("stripe:3/30:x3") == "stripe:4/30:x3" and following("stripe:9/30:x3") is None
    assert [str(s) for s in single_sheets(p)] == ["stripe:3/30", "stripe:13/30", "stripe:23/30"]


def test_one_sheet_is_the_old_tag_and_a_bad_count_says_what_is_allowed():
    assert str(parse("stripe:4/30:x1")) == "stripe:4/30" and parse("stripe:4/30:x1") == parse("stripe:4/30")
    with pytest.raises(PatternError, match=r"index=10 count=30 sheets=3.*ceil\(count/sheets\)"):
        parse("stripe:10/30:x3")
    with pytest.raises(PatternError, match="sheets=31"):
        parse("stripe:0/30:x31")
    with pytest.raises(PatternError, match="only a stripe pattern has sheets"):
        PatternSpec("checker", size=4, sheets=2)
    with pytest.raises(PatternError, match="sheet_columns"):
        stripe_columns(parse("stripe:0/30:x2"), 1024)      # one interval of a two-sheet pattern: refused


@given(st.integers(1, 200).flatmap(lambda n: st.tuples(st.just(n), st.integers(1, n))), st.integers(1, 3000))
def test_a_scan_lights_every_position_once_with_evenly_spaced_sheets(nk, width):
    n, k = nk
    frames = list(stripes(n, k))
    assert len(frames) == math.ceil(n / k)
    lit = [q for f in frames for q in sheet_positions(f)]
    assert sorted(lit) == list(range(n))                          # each position in exactly one frame
    for f in frames:
        pos = sheet_positions(f)
        assert 1 <= len(pos) <= k and set(pos) == {q for q in range(n) if q % len(frames) == f.index}
        assert all(b - a == len(frames) for a, b in zip(pos, pos[1:], strict=False))   # evenly spaced
        assert parse(str(f)) == f
    cols = sorted(c for f in frames for c in sheet_columns(f, width))
    assert cols[0][0] == 0 and cols[-1][1] == width and all(a[1] == b[0] for a, b in zip(cols, cols[1:],
                                                                                          strict=False))


def test_a_stripe_method_scans_ceil_n_over_k_frames():
    pats = Method.POLARIZED_STRIPES.patterns(30, 16, sheets=4)
    assert [str(p) for p in pats][:2] == ["stripe:0/30:x4", "stripe:1/30:x4"] and len(pats) == 8


def test_the_pattern_message_carries_the_sheets_and_version_3_reads_as_one_sheet():
    msg = decode(encode(Pattern.of("stripe:2/30:x5", scan_id=4, step=2)))
    assert (msg.index, msg.count, msg.sheets, str(msg.spec())) == (2, 30, 5, "stripe:2/30:x5")
    head = msgpack.unpackb(encode(msg)[0])
    assert head[1] == 4                                           # version 4 on the wire
    head[1] = 3                                                   # a version 3 header has 10 fields
    old = decode([msgpack.packb(head[:-1])])
    assert old.sheets == 1 and str(old.spec()) == "stripe:2/30"   # ... and the old meaning


def test_a_version_1_scan_event_reads_as_one_sheet():
    frames = encode(ScanEvent(scan_id=3, event="start", method="stripes", stripes=30, sheets=3))
    head = msgpack.unpackb(frames[0])
    assert head[1] == 2 and head[-1] == 3
    head[1] = 1
    old = decode([msgpack.packb(head[:-1])])
    assert (old.stripes, old.sheets) == (30, 1)
