"""Schema versions (msgs/base.py ``older``): a message of an earlier version that lacks only trailing
fields with defaults decodes with those defaults — on the wire and from a recording — and anything else is
refused."""

import json

import msgpack
import pytest
from polarstripe.msgs import MessageError, Pattern, decode, unpack
from polarstripe.msgs.base import Message, message
from polarstripe.runtime.bag import BagWriter
from polarstripe.runtime.bag_reader import BagReader


def _v1_frames(type_name, *values):
    """A header as a build of version 1 wrote it: [type, version, stamp_ns, seq, frame_id, *values]."""
    return [msgpack.packb([type_name, 1, 5, 0, "", *values])]


def test_a_version_1_pattern_reads_with_the_fields_later_versions_added_at_their_defaults():
    msg = decode(_v1_frames("pattern", "stripe", 3, 30, 0, 0, 7, 2))
    assert isinstance(msg, Pattern) and Pattern.VERSION == 4
    assert (msg.kind, msg.index, msg.count, msg.scan_id, msg.step) == ("stripe", 3, 30, 7, 2)
    assert (msg.axis, msg.inverse, msg.xor, msg.sheets) == ("", False, -1, 1)


def test_a_version_1_medium_estimate_has_no_mean_cosine_and_no_reason():
    msg = decode(_v1_frames("medium_estimate", 0.6, 5.0, 4))
    assert (msg.p, msg.sigma_t_per_m, msg.scan_id) == (0.6, 5.0, 4)
    assert msg.mean_cosine is None and msg.p_std is None and msg.reason == ""


def test_a_version_1_frame_reads_as_no_mosaic():
    import numpy as np
    from polarstripe.msgs import Frame, encode
    frames = encode(Frame(image=np.zeros((2, 2), np.uint16), exposure_s=0.01, step=3))
    head = msgpack.unpackb(frames[0])
    head[1] = 1
    msg = decode([msgpack.packb(head[:-1]), *frames[1:]])     # version 1: no mosaic_deg
    assert isinstance(msg, Frame) and Frame.VERSION == 2 and msg.step == 3 and msg.mosaic_deg == []


def test_an_older_version_with_another_field_count_or_an_unknown_version_is_refused():
    with pytest.raises(MessageError, match="unknown schema version 1"):
        decode(_v1_frames("pattern", "stripe", 3, 30))  # version 1 had 7 fields: not a version 1 header
    frames = [msgpack.packb(["pattern", 0, 5, 0, "", "flood", 0, 0, 0, 0, 0, 0])]
    with pytest.raises(MessageError, match="unknown schema version 0"):
        decode(frames)
    frames = [msgpack.packb(["pattern", [1], 5, 0, "", "flood"])]
    with pytest.raises(MessageError, match="version"):
        decode(frames)  # an unhashable version is one clear error, not a TypeError


def test_an_older_version_may_only_lack_fields_that_have_defaults():
    with pytest.raises(TypeError, match="trailing fields that have defaults"):
        @message("test_versions_bad", version=2, older={1: 0})
        class Bad(Message):
            needed: int


def test_a_recording_of_version_1_patterns_replays(tmp_path):
    """A bag whose pattern channel says version 1 (as written before Gray codes) opens and decodes: the
    channel's schema and each payload (``pack``'s map form) as the older build wrote them."""
    path = tmp_path / "old.mcap"
    old = {"type": "pattern", "version": 1, "stamp_ns": 5, "seq": 0, "frame_id": "",
           "fields": {"kind": "stripe", "index": 2, "count": 10, "size": 0, "shift": 0, "scan_id": 3,
                      "step": 1}}
    schema = {"properties": {"type": {"const": "pattern"}, "version": {"const": 1}}}
    with BagWriter(path) as bag:
        cid = bag.register("/rig/emitter/pattern", "polarstripe.pattern", json.dumps(schema).encode(),
                           {"type": "pattern", "version": "1"})
        bag.add_payload(cid, [msgpack.packb(old)], log_time_ns=10, publish_time_ns=5, sequence=0)
    with BagReader(path) as bag:
        assert bag.topics["/rig/emitter/pattern"].version == 1
        msgs = [m for _, _, m in bag.messages()]
    assert [(m.kind, m.index, m.count, m.scan_id, m.step, m.axis, m.inverse) for m in msgs] == \
        [("stripe", 2, 10, 3, 1, "", False)]


def test_a_version_1_map_with_a_field_of_version_2_is_refused():
    old = {"type": "pattern", "version": 1, "stamp_ns": 5, "seq": 0, "frame_id": "",
           "fields": {"kind": "stripe", "index": 2, "count": 10, "size": 0, "shift": 0, "scan_id": 3,
                      "step": 1, "axis": "col"}}
    with pytest.raises(MessageError, match="unknown field"):
        unpack(msgpack.packb(old))


def test_a_version_2_pattern_reads_without_an_xor_base():
    frames = [msgpack.packb(["pattern", 2, 5, 0, "", "gray", 3, 0, 0, 0, 7, 2, "row", True])]
    msg = decode(frames)
    assert (msg.kind, msg.index, msg.axis, msg.inverse, msg.xor) == ("gray", 3, "row", True, -1)
    assert str(msg.spec()) == "gray:3:row:1"
    assert str(Pattern.of("gray:3:row:1:xor2").spec()) == "gray:3:row:1:xor2"
