"""The bag reader (runtime/bag_reader.py) beyond test_bag.py: topic names, channels it must refuse, a type
this build does not know, the time filter, and the files check_file and recover must turn away."""

from __future__ import annotations

import json

import pytest
from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.records import Header as McapHeader
from polarstripe.msgs import Header, Log, PolarizerCommand, json_schema, pack
from polarstripe.runtime.bag import MAGIC, BagError, BagWriter
from polarstripe.runtime.bag_reader import BagReader, TopicSummary, check_file, recover


def _log(i: int, seq: int | None = None) -> Log:
    header = Header(stamp_ns=10 + i, seq=i if seq is None else seq)
    return Log(level="INFO", node="n", text=f"line {i}", header=header)


def _bag(path, *, namespace="/rig", topics=("/rig/talker/chatter", "/rig/listener/chatter", "/rig/log")):
    with BagWriter(path) as w:
        w.add_metadata("launch", {"launch": "demo", "namespace": namespace})
        for i in range(4):
            for k, t in enumerate(topics):
                w.add_message(t, _log(i), log_time_ns=1_000 * i + k)
    return path


def _foreign(path, *, schema: dict | None, message_encoding="msgpack", schema_encoding="jsonschema",
             tname="ghost"):
    """A bag with one channel whose schema the test chooses (default: a type no build declares)."""
    if schema is None:
        schema = json_schema(Log)
        schema["properties"]["type"]["const"] = tname
        schema["title"] = f"polarstripe/{tname}"
    with BagWriter(path) as w:
        cid = w.register("/x/ghost", f"polarstripe/{tname}", json.dumps(schema).encode(), {}, schema_encoding,
                         message_encoding)
        w.add_payload(cid, [b"\x80"], log_time_ns=5, publish_time_ns=5, sequence=0)
        good = w.channel("/x/cmd", PolarizerCommand)
        msg = PolarizerCommand(target_deg=1.5, header=Header(stamp_ns=1))
        w.add_payload(good, [pack(msg)], log_time_ns=6, publish_time_ns=1, sequence=0)
    return path


# ---- topic names ------------------------------------------------------------------------------------------
def test_topics_resolve_in_the_recorded_namespace_or_by_a_unique_ending(tmp_path):
    with BagReader(_bag(tmp_path / "a.mcap")) as bag:
        assert bag.resolve_topics(["log"]) == ["/rig/log"]  # the launch's namespace
        assert bag.resolve_topics(["talker/chatter", "/rig/log"]) == ["/rig/talker/chatter", "/rig/log"]
        assert bag.resolve_topics(["log"], namespace="/other") == ["/rig/log"]  # unique ending
        with pytest.raises(BagError, match=r"no topic 'chatter' \(has /rig/talker/chatter, "):
            bag.resolve_topics(["chatter"])  # two topics end in /chatter
        with pytest.raises(BagError, match="no topic '/log'"):
            bag.resolve_topics(["/log"])  # a full name is taken as it is


def test_raw_is_in_log_time_order_and_filters_by_topic_and_start(tmp_path):
    with BagReader(_bag(tmp_path / "a.mcap")) as bag:
        times = [t for _, t, _, _ in bag.raw()]
        assert times == sorted(times) and len(times) == 12
        got = [(topic, t, seq) for topic, t, seq, _ in bag.raw(["/rig/log"], start_ns=2_000)]
        assert got == [("/rig/log", 2_002, 2), ("/rig/log", 3_002, 3)]
        with pytest.raises(BagError, match="no topic '/nope'"):
            list(bag.raw(["/nope"]))


def test_summary_counts_and_times_per_topic(tmp_path):
    with BagReader(_bag(tmp_path / "a.mcap")) as bag:
        s = bag.topics["/rig/listener/chatter"]
        assert (s.type, s.version, s.known, s.count, s.first_ns, s.last_ns) == ("log", 1, True, 4, 1, 3_001)
        assert s.rate_hz == pytest.approx(3 / 3_000e-9)
        assert (bag.start_ns, bag.end_ns, bag.message_count) == (0, 3_002, 12)
        assert bag.duration_s == pytest.approx(3.002e-6)
        assert bag.compression == ["none"]


@pytest.mark.parametrize(
    "count, first, last, rate",
    [(0, 0, 0, 0.0), (1, 5, 5, 0.0), (3, 7, 7, 0.0), (3, 0, 2_000_000_000, 1.0), (11, 0, 10**9, 10.0)],
)
def test_rate_needs_two_messages_and_a_time_span(count, first, last, rate):
    assert TopicSummary("/t", "log", 1, True, count, first, last).rate_hz == pytest.approx(rate)


def test_sequence_gaps_of_chosen_topics(tmp_path):
    path = tmp_path / "g.mcap"
    with BagWriter(path) as w:
        for k, seq in enumerate([0, 1, 5, 6, 7, 10]):
            w.add_message("/a", _log(k, seq), log_time_ns=k)
        w.add_message("/b", _log(0), log_time_ns=100)
    with BagReader(path) as bag:
        assert bag.sequence_gaps(["/a"]) == {"/a": 3 + 2}
        assert bag.sequence_gaps() == {"/a": 5, "/b": 0}


# ---- channels it reads and channels it refuses ----------------------------------------------------------
def test_a_type_this_build_does_not_know_is_listed_but_not_decoded(tmp_path):
    with BagReader(_foreign(tmp_path / "f.mcap", schema=None)) as bag:
        ghost = bag.topics["/x/ghost"]
        assert (ghost.type, ghost.known, ghost.count) == ("ghost", False, 1) and bag.types["/x/ghost"] is None
        with pytest.raises(BagError, match=r"'/x/ghost': message type 'ghost' is not known to this build"):
            list(bag.messages())
        [(topic, t, msg)] = list(bag.messages(["/x/cmd"]))  # the other topics still read
        assert (topic, t, msg.target_deg) == ("/x/cmd", 6, 1.5)
        assert [r[0] for r in bag.raw()] == ["/x/ghost", "/x/cmd"]  # raw bytes need no type


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"schema": json_schema(Log), "message_encoding": "json"},
         r"message encoding 'json' with schema encoding 'jsonschema' is not a polarstripe channel"),
        ({"schema": json_schema(Log), "schema_encoding": "protobuf"}, "is not a polarstripe channel"),
        ({"schema": {"type": "object"}}, "schema 'polarstripe/ghost' is not a polarstripe message schema"),
        ({"schema": {"properties": {"type": {"const": 3}, "version": {"const": 1}}}}, "bad type 3"),
        ({"schema": {"properties": {"type": {"const": "log"}, "version": {"const": "1"}}}},
         "bad type 'log' or version '1'"),
    ],
    ids=["json-messages", "protobuf-schema", "no-consts", "int-type", "str-version"],
)
def test_channels_that_are_not_polarstripe_ones_are_refused_at_open(tmp_path, kw, match):
    path = _foreign(tmp_path / "f.mcap", **kw)
    with pytest.raises(BagError, match=match) as info:
        BagReader(path)
    assert str(path) in str(info.value) and "'/x/ghost'" in str(info.value)


def test_a_bag_without_a_summary_is_sent_to_recover(tmp_path):
    rb = RecordBuilder()
    McapHeader(profile="", library="hand-made").write(rb)
    DataEnd(data_section_crc=0).write(rb)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(rb)
    path = tmp_path / "nosummary.mcap"
    path.write_bytes(MAGIC + rb.end() + MAGIC)
    with pytest.raises(BagError, match=r"no summary section \(not indexed\); run 'polarstripe bag recover"):
        BagReader(path)
    r = recover(path, tmp_path / "fixed.mcap")
    assert (r.messages, r.chunks, r.stopped) == (0, 0, "")
    with BagReader(tmp_path / "fixed.mcap") as bag:
        assert bag.topics == {} and bag.message_count == 0


def test_garbage_between_the_magics_is_unreadable_not_a_traceback(tmp_path):
    path = tmp_path / "garbage.mcap"
    path.write_bytes(MAGIC + bytes(range(256)) * 2 + MAGIC)
    with pytest.raises(BagError, match=r"unreadable MCAP \("):
        BagReader(path)


# ---- check_file and recover: what they turn away ---------------------------------------------------------
def test_check_file_errors_name_the_file(tmp_path):
    with pytest.raises(BagError, match="is a directory, not an MCAP file"):
        check_file(tmp_path)
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(BagError, match=r"empty.mcap: not an MCAP file \(starts with b''\)"):
        check_file(tmp_path / "empty.mcap")
    (tmp_path / "magics.mcap").write_bytes(MAGIC + MAGIC)  # both magics, nothing between: still truncated
    with pytest.raises(BagError, match=r"truncated MCAP file \(16 bytes"):
        check_file(tmp_path / "magics.mcap")
    good = _bag(tmp_path / "ok.mcap")
    assert check_file(good) == good.stat().st_size


def test_recover_refuses_to_overwrite_its_input(tmp_path):
    src = _bag(tmp_path / "a.mcap")
    before = src.read_bytes()
    with pytest.raises(BagError, match="output .* is the input; choose another file"):
        recover(src, tmp_path / "." / "a.mcap")
    assert src.read_bytes() == before


def test_recover_counts_per_topic_and_keeps_the_launch_metadata(tmp_path):
    r = recover(_bag(tmp_path / "a.mcap"), tmp_path / "b.mcap", compression="zstd")
    assert r.topics == {"/rig/talker/chatter": 4, "/rig/listener/chatter": 4, "/rig/log": 4}
    with BagReader(tmp_path / "b.mcap") as bag:
        assert bag.metadata["launch"] == {"launch": "demo", "namespace": "/rig"}
        assert bag.compression == ["zstd"]
        assert [m.text for _, _, m in bag.messages(["/rig/log"])] == [f"line {i}" for i in range(4)]
