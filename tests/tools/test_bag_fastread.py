"""The exports' zero-copy reader gives what BagReader gives: the same payloads in the same order, and
messages equal to ``unpack``'s with arrays that view the file's mapping; for uncompressed and compressed
chunks, with a time range."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.msgs import unpack
from polarstripe.runtime.bag import BagWriter
from polarstripe.runtime.bag_reader import BagReader
from polarstripe.tools.bag_fastread import BIG, FastReader, parse_packed


def _same(a, b) -> None:
    assert type(a) is type(b) and a.header == b.header
    for name, _ in type(a).FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, dict):
            assert x.keys() == y.keys(), name
            for k in x:
                assert np.array_equal(x[k], y[k]) if isinstance(x[k], np.ndarray) else x[k] == y[k], (name, k)
        elif isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y), name
        else:
            assert x == y, name


@pytest.mark.parametrize(("compression", "mapped"), [("none", False), ("none", True), ("zstd", False),
                                                     ("lz4", False)])
def test_fast_reader_matches_bag_reader(tmp_path, make_rig_bag, compression, mapped):
    pytest.importorskip({"none": "mcap", "zstd": "zstandard", "lz4": "lz4"}[compression])
    src = make_rig_bag(tmp_path / "big.mcap", scans=1, stripes=3, shape=(200, 240))  # frames of 96 KB
    path = tmp_path / f"{compression}.mcap"
    with BagReader(src.path) as b, BagWriter(path, compression=compression, chunk_size=300_000) as w:
        for topic, log, msg in b.messages():
            w.add_message(topic, msg, log_time_ns=log)
    with BagReader(path) as bag:
        topics = list(bag.topics)
        want = list(bag.raw(topics))
        fast = FastReader(bag, mapped=mapped)
        got = list(fast.raw(topics))
        assert [(t, log, bytes(d)) for t, log, d in got] == [(t, log, bytes(d)) for t, log, _, d in want]
        big = 0
        for (topic, _, data), (_, _, _, blob) in zip(got, want, strict=True):
            m = parse_packed(data, topic=topic, expect=bag.types[topic])
            _same(m, unpack(blob, topic=topic, expect=bag.types[topic]))
            if data.nbytes >= BIG:
                big += 1
                arrays = [m.image] if hasattr(m, "image") else list(m.images.values())
                if compression == "none":  # views of the chunk read once, not copies
                    assert all(not a.flags.owndata and not a.flags.writeable for a in arrays)
        assert big >= 6
        lo, hi = want[5][1], want[20][1]
        assert [(t, log) for t, log, _ in fast.raw(topics, lo, hi)] == [
            (t, log) for t, log, _, _ in want if lo <= log <= hi]
        del m, got
        fast.close()


def test_parse_packed_falls_back_to_unpack_for_what_it_does_not_expect(tmp_path, make_rig_bag):
    src = make_rig_bag(tmp_path / "big.mcap", scans=1, stripes=1, shape=(200, 240))
    with BagReader(src.path) as bag:
        (topic, _, _, blob), = [r for r in bag.raw(["/rig/camera/frame"])][:1]
        cls = bag.types[topic]
    broken = bytearray(blob)
    broken[0] = 0xC1  # never used in MessagePack
    with pytest.raises(Exception, match="not a MessagePack map"):
        parse_packed(memoryview(bytes(broken)), topic=topic, expect=cls)
    _same(parse_packed(memoryview(blob), topic=topic, expect=cls), unpack(blob, expect=cls))
