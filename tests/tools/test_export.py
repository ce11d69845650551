"""``polarstripe bag export``: a recording read back by the other side's own readers. The ROS 2 bag with
``rosbags`` (every message decodes, camera frames equal the recorded ones bit for bit, stamps monotone per
topic, tf and camera info present), the Foxglove MCAP with ``mcap`` and the protobuf schemas it carries
(the same check); the options; bad input as one line with nothing half-written left behind."""

from __future__ import annotations

import json
import math
from collections import defaultdict

import numpy as np
import pytest
from polarstripe.msgs import unpack
from polarstripe.nodes.rig_geometry import pinhole
from polarstripe.runtime.bag import BagError, BagWriter
from polarstripe.tools.bag_export import ExportOptions, export
from polarstripe.tools.cli import main

rosbags = pytest.importorskip("rosbags", reason="CI installs the test extra (rosbags)")
pytest.importorskip("foxglove", reason="CI installs the test extra (foxglove-sdk)")
pytest.importorskip("google.protobuf", reason="CI installs the test extra (protobuf)")

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

CAM = "/rig/camera/frame"


def read_ros2(path):
    """Every message of a rosbag2 decoded by rosbags: [(topic, type, log time, message)]."""
    out = []
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        for conn, ts, raw in r.messages():
            out.append((conn.topic, conn.msgtype, ts, r.deserialize(raw, conn.msgtype)))
    return out


def proto_class(name: str, data: bytes):
    """The message class of a protobuf schema record (a FileDescriptorSet), as the Foxglove app builds it."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(data)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def read_foxglove(path):
    """Every message of a Foxglove MCAP decoded from its own schemas: [(topic, schema, log time, message)]."""
    out, classes = [], {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, ch, m in reader.iter_messages():
            if ch.message_encoding == "protobuf":
                assert schema.encoding == "protobuf"
                if schema.id not in classes:
                    classes[schema.id] = proto_class(schema.name, schema.data)
                cls = classes[schema.id]
                out.append((ch.topic, schema.name, m.log_time, cls.FromString(m.data)))
            else:
                assert (ch.message_encoding, schema.encoding) == ("json", "jsonschema")
                out.append((ch.topic, schema.name, m.log_time, json.loads(m.data)))
    return out


def _monotone(rows) -> None:
    last = defaultdict(int)
    for topic, _, ts, _ in rows:
        assert ts >= last[topic], topic
        last[topic] = ts


def test_ros2_export_reads_back_with_rosbags(rig_bag, tmp_path):
    out = tmp_path / "run_ros2"
    res = export(rig_bag.path, out, "ros2", ExportOptions(progress=False))
    assert (out / "metadata.yaml").is_file() and (out / "run_ros2.mcap").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap", "run_ros2"]  # no temporary left
    rows = read_ros2(out)
    assert len(rows) == sum(res.written.values())
    _monotone(rows)
    by = defaultdict(list)
    for topic, typ, ts, m in rows:
        by[topic, typ].append((ts, m))
    # camera frames: bit for bit, stamped with the log time, with their info and camera info
    frames = rig_bag.frames()
    images = by[f"{CAM}/image", "sensor_msgs/msg/Image"]
    assert len(images) == len(frames)
    for (ts, m), (log, f) in zip(images, frames, strict=True):
        assert ts == log and m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == log
        assert (m.encoding, m.height, m.width, m.step, m.is_bigendian) == ("mono16", 48, 64, 128, 0)
        assert m.header.frame_id == "camera"
        assert np.array_equal(m.data.view("<u2").reshape(48, 64), f.image)
    infos = [m for _, m in by[f"{CAM}/info", "polarstripe_msgs/msg/FrameInfo"]]
    assert [(i.pattern, i.polarizer_deg, i.scan_id, i.step, i.stamp_ns) for i in infos] == [
        (f.pattern, f.polarizer_deg, f.scan_id, f.step, f.header.stamp_ns) for _, f in frames]
    (ts0, info0), *_ = by[f"{CAM}/camera_info", "sensor_msgs/msg/CameraInfo"]
    want = pinhole(60.0, 64, 48)
    assert (info0.width, info0.height, info0.distortion_model) == (64, 48, "plumb_bob")
    assert np.allclose(info0.k, want.k) and np.allclose(info0.p, want.p)
    aux = by["/rig/aux/frame/image", "sensor_msgs/msg/Image"][0][1]
    assert aux.encoding == "mono8"
    assert np.array_equal(aux.data.reshape(24, 32), rig_bag.frames("/rig/aux/frame")[0][1].image)
    # tf: tank -> camera -> polarizer, tank -> projector (at the truth's separation), first of all, latched
    (tf_ts, tf), = by["/tf_static", "tf2_msgs/msg/TFMessage"]
    assert tf_ts == rows[0][2]
    kids = {t.child_frame_id: t for t in tf.transforms}
    assert {(t.header.frame_id, c) for c, t in kids.items()} == {
        ("tank", "camera"), ("camera", "polarizer"), ("tank", "projector")}
    pos = kids["projector"].transform.translation
    assert math.isclose(math.hypot(pos.x, pos.y, pos.z), 0.2)
    q = kids["camera"].transform.rotation
    assert math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0)
    # the pattern as a projector image with its own camera info
    pat = by["/rig/emitter/pattern/image", "sensor_msgs/msg/Image"][1][1]
    lit = pat.data.reshape(30, 40).max(axis=0)
    assert pat.encoding == "mono8" and list(np.nonzero(lit)[0]) == list(range(10, 20))  # stripe 1 of 4
    assert by["/rig/emitter/pattern/camera_info", "sensor_msgs/msg/CameraInfo"][0][1].width == 40
    # plottable numbers
    joints = [m for _, m in by["/rig/polarizer/state/joint_states", "sensor_msgs/msg/JointState"]]
    assert joints[1].name == ["analyzer"] and math.isclose(joints[1].position[0], math.pi / 2)
    metrics = [m for _, m in by["/rig/compositor/composite/metrics", "polarstripe_msgs/msg/CompositeMetrics"]]
    assert [round(m.contrast, 3) for m in metrics] == [0.41, 0.42]
    assert metrics[0].method == "polarized_stripes"
    assert math.isnan(metrics[0].error_vs_truth) and "frames" in metrics[0].names
    est = by["/rig/medium/estimate", "polarstripe_msgs/msg/MediumEstimate"][0][1]
    assert est.p == 0.7 and math.isnan(est.sigma_t_per_m)
    plan = by["/rig/planner/plan", "polarstripe_msgs/msg/Plan"][0][1]
    assert [c.name for c in plan.curves] == ["separation_m", "quality"] and len(plan.curves[1].values) == 6
    comp = by["/rig/compositor/composite/composite", "sensor_msgs/msg/Image"][0][1]
    sent = rig_bag.sent["/rig/compositor/composite"][0][1]
    assert comp.encoding == "32FC1"
    assert np.array_equal(comp.data.view("<f4").reshape(48, 64), sent.images["composite"])
    truth = by["/rig/simulator/truth/S", "sensor_msgs/msg/Image"][0][1]
    assert truth.encoding == "64FC1"
    assert by["/rig/simulator/truth/chart_band", "sensor_msgs/msg/Image"][0][1].encoding == "32SC1"
    logs = [m for _, m in by["/rosout", "rcl_interfaces/msg/Log"]]
    assert [(m.name, m.level, m.msg) for m in logs] == [
        ("sequencer", 20, "scan starts"), ("compositor", 30, "done")]
    (_, packed), = by["/rig/polarizer/mount", "polarstripe_msgs/msg/Packed"]
    assert packed.type == "analyzer_mount" and unpack(bytes(packed.msgpack)).inserted is True


def test_foxglove_export_reads_back_with_mcap_and_protobuf(rig_bag, tmp_path):
    out = tmp_path / "run.foxglove.mcap"
    res = export(rig_bag.path, out, "foxglove", ExportOptions(progress=False))
    rows = read_foxglove(out)
    assert len(rows) == sum(res.written.values())
    _monotone(rows)
    by = defaultdict(list)
    for topic, schema, ts, m in rows:
        by[topic, schema].append((ts, m))
    frames = rig_bag.frames()
    images = by[f"{CAM}/image", "foxglove.RawImage"]
    assert len(images) == len(frames)
    for (ts, m), (log, f) in zip(images, frames, strict=True):
        assert ts == log and m.timestamp.seconds * 10**9 + m.timestamp.nanos == log
        assert (m.encoding, m.width, m.height, m.step, m.frame_id) == ("mono16", 64, 48, 128, "camera")
        assert np.array_equal(np.frombuffer(m.data, "<u2").reshape(48, 64), f.image)
    cal = by[f"{CAM}/camera_info", "foxglove.CameraCalibration"][0][1]
    assert (cal.width, cal.height) == (64, 48) and np.allclose(cal.K, pinhole(60.0, 64, 48).k)
    (_, tf), = by["/tf_static", "foxglove.FrameTransforms"]
    assert {(t.parent_frame_id, t.child_frame_id) for t in tf.transforms} == {
        ("tank", "camera"), ("camera", "polarizer"), ("tank", "projector")}
    logs = [m for _, m in by["/rig/log", "foxglove.Log"]]
    assert [(m.name, m.message) for m in logs] == [("sequencer", "scan starts"), ("compositor", "done")]
    state = by["/rig/polarizer/state", "polarstripe.PolarizerState"][1][1]
    assert state["angle_deg"] == 90.0 and state["settled"] is True
    metrics = [m for _, m in by["/rig/compositor/composite/metrics", "polarstripe.CompositeMetrics"]]
    assert [m["method"] for m in metrics] == ["polarized_stripes"] * 2
    assert metrics[0]["error_vs_truth"] is None
    est = by["/rig/medium/estimate", "polarstripe.MediumEstimate"][0][1]
    assert est["sigma_t_per_m"] is None and est["p"] == 0.7
    info = by[f"{CAM}/info", "polarstripe.FrameInfo"][3][1]
    assert (info["pattern"], info["polarizer_deg"], info["step"]) == ("stripe:3/4", 0.0, 3)
    mask = by["/rig/simulator/truth/chart_high", "foxglove.RawImage"][0][1]
    assert mask.encoding == "mono8" and set(np.unique(np.frombuffer(mask.data, np.uint8))) <= {0, 255}
    packed = by["/rig/polarizer/mount", "polarstripe.analyzer_mount"][0][1]
    assert packed["fields"] == {"inserted": True}
    with open(out, "rb") as f:  # the recording's context rides along
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert meta["launch"]["launch"] == "synthetic" and meta["export"]["source"] == str(rig_bag.path)


def test_options_topics_time_range_and_image_decimation(rig_bag, tmp_path):
    frames = rig_bag.frames()
    res = export(rig_bag.path, tmp_path / "a", "ros2",
                 ExportOptions(topics=["camera/*", "/rig/log"], image_every=3, progress=False))
    topics = {t for t, _ in res.written}
    assert topics == {f"{CAM}/image", f"{CAM}/info", f"{CAM}/camera_info", "/rosout", "/tf_static"}
    kept = [ts for t, _, ts, _ in read_ros2(tmp_path / "a") if t == f"{CAM}/image"]
    assert kept == [log for log, _ in frames[::3]] and res.skipped == len(frames) - len(kept)
    t0 = rig_bag.sent["/rig/log"][0][0]  # the recording's first message
    start_s, end_s = (frames[2][0] - t0) / 1e9, (frames[5][0] - t0) / 1e9
    res = export(rig_bag.path, tmp_path / "b.mcap", "foxglove",
                 ExportOptions(topics=["camera/frame"], start_s=start_s, end_s=end_s, progress=False))
    got = [ts for t, _, ts, _ in read_foxglove(tmp_path / "b.mcap") if t == f"{CAM}/image"]
    assert got == [log for log, _ in frames[2:6]]


def test_cli_export_and_its_errors_are_one_line(rig_bag, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["bag", "export", str(rig_bag.path), str(out), "--to", "ros2", "--no-progress"]) == 0
    assert "sensor_msgs/msg/Image" in capsys.readouterr().out

    def fails(*args, match: str):
        before = sorted(p.name for p in tmp_path.iterdir())
        assert main(["bag", "export", *map(str, args), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("polarstripe bag: error: ") and err.count("\n") == 1, err
        assert "Traceback" not in err
        assert match in err, err
        assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing half-written
    fails(rig_bag.path, out, "--to", "ros2", match="exists")
    fails(rig_bag.path, tmp_path / "x", "--to", "foxglove", "--topics", "nothing/here",
          match="no topic matches")
    empty = tmp_path / "empty.mcap"
    BagWriter(empty).start().finish()
    fails(empty, tmp_path / "y", "--to", "ros2", match="no messages to export")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(rig_bag.path.read_bytes()[:5000])
    fails(cut, tmp_path / "z", "--to", "foxglove", match="truncated")
    alien = tmp_path / "alien.mcap"
    with BagWriter(alien) as w:
        cid = w.register("/x", "foo.Bar", b"", {}, "protobuf", "protobuf")
        w.add_payload(cid, [b"\x08\x01"], log_time_ns=1, publish_time_ns=1, sequence=0)
    fails(alien, tmp_path / "w", "--to", "ros2", match="not a polarstripe channel")
    fails(rig_bag.path, tmp_path / "v", "--to", "ros2", "--image-every", "0", match="--image-every")
    fails(rig_bag.path, tmp_path / "v", "--to", "ros2", "--start", "1e6", match="no messages to export")


def test_interrupted_export_leaves_nothing(rig_bag, tmp_path, monkeypatch):
    from polarstripe.tools import export_ros2

    def boom(self, v):
        raise KeyboardInterrupt

    monkeypatch.setattr(export_ros2.Ros2Sink, "write", boom)
    with pytest.raises(KeyboardInterrupt):
        export(rig_bag.path, tmp_path / "out", "ros2", ExportOptions(progress=False))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]


def test_a_rig_without_a_scene_has_no_tf_unless_given_one(tmp_path, make_rig_bag):
    bag = make_rig_bag(tmp_path / "rig.mcap", scans=1, stripes=2)
    with BagWriter(tmp_path / "plain.mcap") as w:  # the same messages, no launch metadata
        for topic, msgs in bag.sent.items():
            for log, m in msgs:
                w.add_message(topic, m, log_time_ns=log)
    res = export(tmp_path / "plain.mcap", tmp_path / "a", "ros2", ExportOptions(progress=False))
    assert "no scene" in res.geometry and not any(t == "/tf_static" for t, _ in res.written)
    scene = tmp_path / "scene.toml"
    scene.write_text("[camera]\nposition = [0.0, 0.1, 0.0]\nfov_deg = 40.0\n")
    res = export(tmp_path / "plain.mcap", tmp_path / "b", "ros2",
                 ExportOptions(scene=str(scene), progress=False))
    rows = read_ros2(tmp_path / "b")
    (tf,) = [m for t, _, _, m in rows if t == "/tf_static"]
    cam = next(t for t in tf.transforms if t.child_frame_id == "camera")
    assert math.isclose(cam.transform.translation.y, 0.1)
    info = next(m for t, _, _, m in rows if t == f"{CAM}/camera_info")
    assert np.allclose(info.k, pinhole(40.0, 64, 48).k)
    with pytest.raises(BagError, match="--scene"):
        export(tmp_path / "plain.mcap", tmp_path / "c", "ros2",
               ExportOptions(scene=str(tmp_path / "nope.toml")))


def test_a_type_this_build_does_not_know_goes_out_packed(tmp_path):
    import msgpack

    schema = {"properties": {"type": {"const": "mystery"}, "version": {"const": 3}}}
    blob = msgpack.packb({"type": "mystery", "version": 3, "stamp_ns": 5, "seq": 0, "frame_id": "",
                          "fields": {"x": 1.5}})
    path = tmp_path / "mystery.mcap"
    with BagWriter(path) as w:
        cid = w.register("/lab/mystery", "polarstripe/mystery", json.dumps(schema).encode(),
                         {"type": "mystery", "version": "3"})
        w.add_payload(cid, [blob], log_time_ns=10, publish_time_ns=5, sequence=0)
    export(path, tmp_path / "r", "ros2", ExportOptions(progress=False))
    (row,) = [r for r in read_ros2(tmp_path / "r") if r[0] == "/lab/mystery"]
    assert row[1] == "polarstripe_msgs/msg/Packed" and (row[3].type, row[3].version) == ("mystery", 3)
    assert bytes(row[3].msgpack) == blob
    export(path, tmp_path / "f.mcap", "foxglove", ExportOptions(progress=False))
    (row,) = [r for r in read_foxglove(tmp_path / "f.mcap") if r[0] == "/lab/mystery"]
    assert row[1] == "polarstripe.mystery" and row[3]["type"] == "mystery"
