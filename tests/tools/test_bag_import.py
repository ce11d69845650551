"""``polarstripe bag import``: a rosbag2 in the layout the export writes becomes a polarstripe bag that the
replayer's reader opens and the compositor turns into the same composites as the original recording; bad
input is one line and leaves nothing behind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from polarstripe.msgs import Frame, ScanEvent
from polarstripe.nodes.compositor import Compositor
from polarstripe.runtime.bag_reader import BagReader
from polarstripe.runtime.testing import NodeHarness
from polarstripe.tools.bag_export import ExportOptions, export
from polarstripe.tools.bag_import import import_ros2
from polarstripe.tools.cli import main

pytest.importorskip("rosbags", reason="CI installs the test extra (rosbags)")

from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

FIELDS = ("pattern", "polarizer_deg", "exposure_s", "gain", "bit_depth", "scan_id", "step")


@pytest.fixture
def exported(rig_bag, tmp_path) -> Path:
    out = tmp_path / "ros2"
    export(rig_bag.path, out, "ros2", ExportOptions(progress=False))
    return out


def _messages(path) -> dict[str, list]:
    out: dict[str, list] = {}
    with BagReader(path) as bag:
        for topic, log, msg in bag.messages():
            out.setdefault(topic, []).append((log, msg))
    return out


def test_import_gives_back_the_frames_and_what_the_compositor_needs(rig_bag, exported, tmp_path):
    dst = tmp_path / "imported.mcap"
    res = import_ros2(exported, dst, progress=False)
    assert res.namespace == "/rig" and res.unpaired == 0
    got = _messages(dst)
    frames = rig_bag.frames()
    assert len(got["/rig/camera/frame"]) == len(frames)
    for (log, f), (log0, f0) in zip(got["/rig/camera/frame"], frames, strict=True):
        assert log == log0 and f.header.stamp_ns == f0.header.stamp_ns and f.header.seq == f0.header.seq
        assert f.image.dtype == np.uint16 and np.array_equal(f.image, f0.image)
        assert all(getattr(f, k) == getattr(f0, k) for k in FIELDS)
    aux = got["/rig/aux/frame"][0][1]
    assert aux.image.dtype == np.uint8
    assert np.array_equal(aux.image, rig_bag.frames("/rig/aux/frame")[0][1].image)
    for topic in ("/rig/emitter/scan", "/rig/polarizer/state", "/rig/polarizer/cmd", "/rig/emitter/pattern",
                  "/rig/medium/estimate", "/rig/heartbeat", "/rig/polarizer/mount"):
        want = [(log, {k: getattr(m, k) for k, _ in m.FIELDS}) for log, m in rig_bag.sent[topic]]
        assert [(log, {k: getattr(m, k) for k, _ in m.FIELDS}) for log, m in got[topic]] == want, topic
    plan, plan0 = got["/rig/planner/plan"][0][1], rig_bag.sent["/rig/planner/plan"][0][1]
    assert np.array_equal(plan.curves["quality"], plan0.curves["quality"])
    assert [(m.node, m.level, m.text) for _, m in got["/rig/log"]] == [
        (m.node, m.level, m.text) for _, m in rig_bag.sent["/rig/log"]]
    assert "/rig/compositor/composite/composite (sensor_msgs/msg/Image)" in res.skipped
    with BagReader(dst) as bag:  # as the replayer finds its topics
        found = bag.resolve_topics(["camera/frame", "emitter/scan"])
    assert found == ["/rig/camera/frame", "/rig/emitter/scan"]


def _composites(path) -> list:
    """The recording's frames and scan events through the compositor, in log order."""
    h = NodeHarness(Compositor, name="compositor", namespace="/rig",
                    params={"dark_offset_dn": 64.0, "use_truth": False, "done_grace_s": 0.05,
                            "object_free_roi": [0, 48, 0, 16]})
    with BagReader(path) as bag:
        for _, _, msg in bag.messages(["/rig/camera/frame", "/rig/emitter/scan"]):
            h.deliver("camera/frame" if isinstance(msg, Frame) else "emitter/scan", msg)
            if isinstance(msg, ScanEvent) and msg.event == "done":
                h.advance(0.5)
    return h.published("compositor/composite")


def test_the_compositor_makes_the_same_composites_from_the_imported_bag(rig_bag, exported, tmp_path):
    dst = tmp_path / "imported.mcap"
    import_ros2(exported, dst, progress=False)
    want, got = _composites(rig_bag.path), _composites(dst)
    assert [c.scan_id for c in got] == [1, 2] and all(c.metrics["frames"] == 8 for c in got)
    for a, b in zip(got, want, strict=True):
        assert a.images.keys() == b.images.keys()
        for k in a.images:
            assert np.array_equal(a.images[k], b.images[k], equal_nan=True), k


def _rosbag(path: Path, *, log_only: bool = False) -> None:
    ts = get_typestore(Stores.ROS2_JAZZY)
    t = ts.types
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/rosout", "rcl_interfaces/msg/Log", typestore=ts)
        log = t["rcl_interfaces/msg/Log"](stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=0), level=20,
                                          name="cam", msg="hello", file="", function="", line=0)
        w.write(conn, 1_000_000_000, ts.serialize_cdr(log, "rcl_interfaces/msg/Log"))
        if not log_only:
            bad = w.add_connection("/weird", "foo_msgs/msg/Bar", msgdef="this is not a message definition !!",
                                   rihs01="RIHS01_" + "0" * 64)
            w.write(bad, 2_000_000_000, b"\x00\x01\x00\x00")


def test_import_errors_are_one_line_and_leave_nothing(exported, tmp_path, capsys):
    def fails(src, dst, match):
        before = sorted(p.name for p in tmp_path.iterdir())
        assert main(["bag", "import", str(src), "-o", str(dst), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("polarstripe bag: error: ") and err.count("\n") == 1, err
        assert match in err and "Traceback" not in err, err
        assert sorted(p.name for p in tmp_path.iterdir()) == before

    _rosbag(tmp_path / "logs_only", log_only=True)
    fails(tmp_path / "logs_only", tmp_path / "a.mcap", "no camera frames")
    _rosbag(tmp_path / "weird")
    fails(tmp_path / "weird", tmp_path / "a.mcap", "unreadable rosbag2")
    fails(tmp_path / "nowhere", tmp_path / "a.mcap", "no such file")
    fails(exported / "ros2.mcap", tmp_path / "a.mcap", "not a rosbag2 folder")
    (tmp_path / "taken.mcap").write_bytes(b"x")
    fails(exported, tmp_path / "taken.mcap", "exists")
    cut = tmp_path / "cut"
    cut.mkdir()
    meta = (exported / "metadata.yaml").read_text()
    (cut / "metadata.yaml").write_text(meta.replace("ros2.mcap", "cut.mcap"))
    (cut / "cut.mcap").write_bytes((exported / "ros2.mcap").read_bytes()[:30000])
    fails(cut, tmp_path / "a.mcap", "unreadable rosbag2")
    assert main(["bag", "import", str(exported), "-o", str(tmp_path / "ok.mcap"), "--no-progress"]) == 0
    assert "/rig/camera/frame: 16" in capsys.readouterr().out


def test_a_pattern_record_comes_back_with_what_only_its_tag_holds():
    """PatternInfo carries the tag beside the fields: a K-sheet stripe (and a Gray code) comes back whole; a
    record whose tag is not a pattern falls back to its fields."""
    from types import SimpleNamespace

    from polarstripe.tools.bag_import import _record

    def info(tag):
        return SimpleNamespace(tag=tag, kind="stripe", index=2, count=30, size=0, shift=0, scan_id=4, step=7)

    got = _record("PatternInfo", info("stripe:2/30:x3"), 5)
    assert (str(got.spec()), got.sheets, got.scan_id, got.step) == ("stripe:2/30:x3", 3, 4, 7)
    assert str(_record("PatternInfo", info("gray:3:row:1:xor2"), 5).spec()) == "gray:3:row:1:xor2"
    assert str(_record("PatternInfo", info("stripe"), 5).spec()) == "stripe:2/30"
