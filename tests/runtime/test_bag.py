"""The MCAP writer, reader and recover: files read by the mcap package's own reader, every message intact;
chunks closed by age; a torn tail recovered up to the last complete chunk; one clear error per bad input."""

import base64
import json
import subprocess
import sys
import time

import msgpack
import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap.stream_reader import StreamReader
from polarstripe.msgs import Composite, Frame, Header, Log, ScanEvent, json_schema, pack, unpack
from polarstripe.runtime.bag import BagError, BagWriter, payload
from polarstripe.runtime.bag_reader import BagReader, check_file, recover

FUTURE = Frame.VERSION + 1  # a schema version no build of this one knows


def _frame(i: int, shape=(48, 64)) -> Frame:
    rng = np.random.default_rng(i)
    img = rng.integers(0, 4096, size=shape, dtype=np.uint16)
    return Frame(
        image=img,
        exposure_s=0.001 * (i + 1),
        pattern=f"stripe:{i}/8",
        polarizer_deg=float(i),
        scan_id=3,
        step=i,
        header=Header(stamp_ns=1_000_000_000 + i, seq=i, frame_id="cam"),
    )


def _messages(n=6):
    out = []
    for i in range(n):
        out.append(("/rig/camera/frame", _frame(i)))
        out.append(
            ("/rig/log", Log(level="INFO", node="t", text=f"line {i} ü", header=Header(seq=i, stamp_ns=7)))
        )
    comp = Composite(
        images={
            "composite": np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4),
            "saturated": np.zeros((3, 4), np.uint8),
        },
        method="stripes",
        scan_id=3,
        metrics={"contrast": 0.5, "bars": [1, 2], "note": None},
        header=Header(seq=0, stamp_ns=9),
    )
    out.append(("/rig/compositor/composite", comp))
    out.append(
        (
            "/rig/emitter/scan",
            ScanEvent(scan_id=3, event="done", analyzer_deg=[0.0, 90.0], header=Header(seq=0, stamp_ns=11)),
        )
    )
    return out


def _same(a, b) -> None:
    assert type(a) is type(b)
    assert a.header == b.header
    for name, _ in type(a).FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y)
        elif isinstance(x, dict) and any(isinstance(v, np.ndarray) for v in x.values()):
            assert x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x)
        else:
            assert x == y


def _write(path, msgs, **kw):
    with BagWriter(path, **kw) as w:
        for k, (topic, m) in enumerate(msgs):
            w.add_message(topic, m, log_time_ns=5_000 + 1000 * k)
        w.add_metadata("versions", {"polarstripe": "test"})
    return path


@pytest.mark.parametrize("msg", [m for _, m in _messages(2)], ids=lambda m: type(m).__name__)
def test_payload_is_pack_without_copying_the_pixels(msg):
    parts = payload(msg)
    assert b"".join(parts) == pack(msg)
    if isinstance(msg, Frame):
        big = msg.image.nbytes
        assert any(isinstance(p, memoryview) and p.nbytes == big for p in parts) or big < 65536


@pytest.mark.parametrize(
    "arr",
    [
        np.zeros((0, 5), np.uint16),
        np.array(5.0),
        np.ones(3, bool),
        np.arange(6, dtype=">u2").reshape(2, 3),
        np.ones((300, 300), np.complex64),
    ],
    ids=["empty", "0-d", "bool", "big-endian", "complex-large"],
)
def test_payload_of_unusual_arrays_is_pack(arr):
    c = Composite(images={"a": arr}, method="m", header=Header(stamp_ns=1))
    assert b"".join(payload(c)) == pack(c)
    got = unpack(b"".join(payload(c)))
    assert got.images["a"].dtype == arr.dtype and np.array_equal(got.images["a"], arr)


def test_written_messages_are_freed_at_once(tmp_path):
    """Once a chunk is written, nothing of the writer keeps a message's arrays (the recorder's received
    frames) alive: without a reference cycle they are freed by reference counting, not at the next garbage
    collection, so the receive buffers are reused instead of faulting in fresh pages for every frame."""
    import gc
    import weakref

    gc.disable()
    try:
        images = [_frame(i, shape=(512, 640)).image for i in range(2)]
        alive = [weakref.ref(a) for a in images]
        with BagWriter(tmp_path / "a.mcap", chunk_size=1) as w:  # every message closes its chunk
            w.add_message("/c", Composite(images={"a": images[0]}, method="m"))  # an array in a dict
            w.add_message("/f", Frame(image=images[1], exposure_s=0.01))
            del images
            assert [r() for r in alive] == [None, None]
    finally:
        gc.enable()


def test_large_frame_payload_is_a_view_of_the_array():
    f = _frame(1, shape=(512, 640))
    parts = payload(f)
    views = [p for p in parts if isinstance(p, memoryview)]
    assert len(views) == 1 and views[0].nbytes == f.image.nbytes
    assert np.shares_memory(np.frombuffer(views[0], np.uint16), f.image)


@pytest.mark.parametrize("compression", ["none", "zstd", "lz4"])
def test_mcap_reader_reads_every_message_intact(tmp_path, compression):
    msgs = _messages()
    path = _write(tmp_path / "a.mcap", msgs, compression=compression, chunk_size=20_000)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        got = list(reader.iter_messages(log_time_order=True))
    assert len(got) == len(msgs)
    assert len(summary.chunk_indexes) > 1  # small chunks
    assert {ci.compression for ci in summary.chunk_indexes} == {"" if compression == "none" else compression}
    for k, ((topic, sent), (schema, channel, rec)) in enumerate(zip(msgs, got, strict=True)):
        assert channel.topic == topic and channel.message_encoding == "msgpack"
        assert schema.encoding == "jsonschema" and json.loads(schema.data) == json_schema(type(sent))
        assert rec.log_time == 5_000 + 1000 * k
        assert rec.publish_time == sent.header.stamp_ns and rec.sequence == sent.header.seq
        _same(unpack(rec.data, topic=topic), sent)


def test_uncompressed_chunk_crc_is_the_crc_of_its_records(tmp_path):
    import zlib

    from mcap.records import Chunk

    path = _write(tmp_path / "crc.mcap", [("/rig/camera/frame", _frame(i)) for i in range(3)], crc=True)
    with open(path, "rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    assert chunks and all(c.uncompressed_crc == zlib.crc32(c.data) != 0 for c in chunks)
    with open(path, "rb") as f:
        assert len(list(make_reader(f, validate_crcs=True).iter_messages())) == 3


def test_payloads_validate_against_their_json_schema(tmp_path):
    jsonschema = pytest.importorskip("jsonschema")

    def as_json(v):  # how a JSON viewer shows the msgpack payload: bin as base64 strings
        if isinstance(v, bytes):
            return base64.b64encode(v).decode()
        if isinstance(v, dict):
            return {k: as_json(x) for k, x in v.items()}
        if isinstance(v, list):
            return [as_json(x) for x in v]
        return v

    path = _write(tmp_path / "s.mcap", _messages(2))
    with open(path, "rb") as f:
        for schema, _, rec in make_reader(f).iter_messages():
            doc = as_json(msgpack.unpackb(rec.data, raw=False))
            jsonschema.validate(doc, json.loads(schema.data))


def test_bag_reader_summary_and_metadata(tmp_path):
    msgs = _messages(6)
    with BagReader(_write(tmp_path / "b.mcap", msgs)) as bag:
        assert bag.message_count == len(msgs)
        assert bag.topics["/rig/camera/frame"].count == 6
        assert (
            bag.topics["/rig/camera/frame"].type == "frame"
            and bag.topics["/rig/camera/frame"].version == Frame.VERSION
        )
        # log times 5000, 7000, ... 15000 ns on the frame topic: 5 intervals of 2 µs
        assert bag.topics["/rig/camera/frame"].first_ns == 5_000
        assert bag.topics["/rig/camera/frame"].last_ns == 15_000
        assert bag.topics["/rig/camera/frame"].rate_hz == pytest.approx(5 / 10e-6)
        assert bag.metadata["versions"] == {"polarstripe": "test"}
        decoded = list(bag.messages(["/rig/camera/frame"]))
        assert [m.step for _, _, m in decoded] == list(range(6))
        assert bag.sequence_gaps()["/rig/camera/frame"] == 0


def test_sequence_gaps_are_counted(tmp_path):
    msgs = [("/rig/camera/frame", _frame(i)) for i in (0, 1, 4, 5, 9)]
    with BagReader(_write(tmp_path / "g.mcap", msgs)) as bag:
        assert bag.sequence_gaps() == {"/rig/camera/frame": 2 + 3}


def test_chunk_reaches_the_disk_when_it_is_old(tmp_path):
    path = tmp_path / "age.mcap"
    w = BagWriter(path, chunk_size=1 << 30, chunk_age_s=0.05).start()
    w.add_message("/rig/log", Log(level="INFO", node="t", text="slow topic"))

    def on_disk() -> int:
        with open(path, "rb") as f:
            n = 0
            try:
                for _ in NonSeekingReader(f).iter_messages(log_time_order=False):
                    n += 1
            except Exception:  # the file has no footer yet
                pass
            return n

    assert on_disk() == 0  # still in the open chunk
    time.sleep(0.08)
    w.flush_stale()
    assert on_disk() == 1
    w.finish()


def _chunk_ends(path) -> list[tuple[int, int]]:
    """(end offset of each chunk's message indexes, messages in chunks up to it), from the file's index."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    out, total = [], 0
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        with open(path, "rb") as f:
            f.seek(ci.chunk_start_offset)
            chunk = next(iter(StreamReader(f, skip_magic=True, emit_chunks=True).records))
        from mcap.stream_reader import breakup_chunk

        total += sum(1 for r in breakup_chunk(chunk) if type(r).__name__ == "Message")
        out.append((ci.chunk_start_offset + ci.chunk_length + ci.message_index_length, total))
    return out


@pytest.mark.parametrize("cut_fraction", [0.2, 0.55, 0.9])
def test_recover_keeps_every_complete_chunk(tmp_path, cut_fraction):
    msgs = [("/rig/camera/frame", _frame(i)) for i in range(20)]
    full = _write(tmp_path / "full.mcap", msgs, chunk_size=15_000)
    data = full.read_bytes()
    cut = int(len(data) * cut_fraction)
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(data[:cut])
    with pytest.raises(BagError, match="truncated"):
        check_file(torn)
    # the messages of chunks that lie wholly before the cut, from the intact file's own index
    expected = max([n for end, n in _chunk_ends(full) if end - 1 <= cut] + [0])
    r = recover(torn, tmp_path / "fixed.mcap")
    assert r.stopped  # it met the torn tail
    with BagReader(tmp_path / "fixed.mcap") as bag:  # indexed: the seeking reader opens it
        got = [m for _, _, m in bag.messages()]
    assert len(got) >= expected and r.messages == len(got)
    assert len(got) < len(msgs)
    for k, m in enumerate(got):  # a prefix, every message intact
        _same(m, msgs[k][1])


def test_recover_of_a_complete_file_copies_everything(tmp_path):
    msgs = _messages(3)
    r = recover(_write(tmp_path / "ok.mcap", msgs), tmp_path / "copy.mcap")
    assert r.stopped == "" and r.messages == len(msgs)
    with BagReader(tmp_path / "copy.mcap") as bag:
        assert bag.metadata["versions"] == {"polarstripe": "test"}
        for (t, sent), (topic, _, got) in zip(msgs, bag.messages(), strict=True):
            assert topic == t
            _same(got, sent)


def test_bad_inputs_each_give_one_clear_error(tmp_path):
    (tmp_path / "text.mcap").write_text("hello, not a bag\n" * 10)
    with pytest.raises(BagError, match="not an MCAP file"):
        BagReader(tmp_path / "text.mcap")
    with pytest.raises(BagError, match="no such file"):
        BagReader(tmp_path / "missing.mcap")
    full = _write(tmp_path / "f.mcap", _messages(2)).read_bytes()
    (tmp_path / "cut.mcap").write_bytes(full[: len(full) - 30])
    with pytest.raises(BagError, match="truncated MCAP file.*bag recover"):
        BagReader(tmp_path / "cut.mcap")
    # a channel recorded by a newer build, whose 'frame' schema is a version this one does not know
    schema = json_schema(Frame)
    schema["properties"]["version"]["const"] = FUTURE
    with BagWriter(tmp_path / "v2.mcap") as w:
        cid = w.register(
            "/rig/camera/frame",
            "polarstripe/frame",
            json.dumps(schema).encode(),
            {"type": "frame", "version": str(FUTURE)},
        )
        w.add_payload(cid, [b"\x80"], log_time_ns=1, publish_time_ns=1, sequence=0)
    with pytest.raises(BagError, match=rf"'/rig/camera/frame': unknown schema version {FUTURE} of 'frame'"):
        BagReader(tmp_path / "v2.mcap")
    with pytest.raises(BagError, match="not an MCAP file"):
        recover(tmp_path / "text.mcap", tmp_path / "out.mcap")


@pytest.mark.parametrize(
    "name, needle",
    [("text.mcap", "not an MCAP file"), ("cut.mcap", "truncated"),
     ("v2.mcap", f"unknown schema version {FUTURE}")],
)
def test_bag_info_prints_one_line_errors(tmp_path, name, needle):
    (tmp_path / "text.mcap").write_bytes(b"PK\x03\x04 a zip, not a bag")
    full = _write(tmp_path / "f.mcap", _messages(2)).read_bytes()
    (tmp_path / "cut.mcap").write_bytes(full[: len(full) // 2])
    schema = json_schema(Frame)
    schema["properties"]["version"]["const"] = FUTURE
    with BagWriter(tmp_path / "v2.mcap") as w:
        w.register("/rig/camera/frame", "polarstripe/frame", json.dumps(schema).encode(), {})
    r = subprocess.run(
        [sys.executable, "-m", "polarstripe", "bag", "info", str(tmp_path / name)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2
    assert r.stdout == "" and len(r.stderr.strip().splitlines()) == 1
    assert needle in r.stderr and "Traceback" not in r.stderr


def test_bag_info_and_recover_commands(tmp_path):
    full = _write(tmp_path / "f.mcap", [("/rig/camera/frame", _frame(i)) for i in range(10)], chunk_size=9000)
    r = subprocess.run(
        [sys.executable, "-m", "polarstripe", "bag", "info", "--scan", str(full)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    row = next(line for line in r.stdout.splitlines() if line.startswith("/rig/camera/frame"))
    assert row.split()[1:4] == ["frame", f"v{Frame.VERSION}", "10"]
    assert "decoded:     10 messages" in r.stdout
    data = full.read_bytes()
    (tmp_path / "torn.mcap").write_bytes(data[: len(data) * 3 // 4])
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "polarstripe",
            "bag",
            "recover",
            str(tmp_path / "torn.mcap"),
            "-o",
            str(tmp_path / "fixed.mcap"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert "stopped at the damaged tail" in r.stdout
    with BagReader(tmp_path / "fixed.mcap") as bag:
        assert 0 < bag.message_count < 10
