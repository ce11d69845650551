"""The ROS 2 types the bag export and the live bridge send: RIHS01 hashes against values published by ROS 2
(rmw_zenoh's design document, a ROS 2 log), against ros2-pyterfaces' own computation, and against the
third-party client's computation from the shipped ``ros2/polarstripe_msgs`` files; the package equal to what
``polarstripe ros2 msgs`` generates; its records equal to the messages of ``msgs/``."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from polarstripe import __version__
from polarstripe.msgs import REGISTRY, ScanRequest
from polarstripe.nodes.rig_views import RECORDS
from polarstripe.nodes.ros2_schemas import SERVICES, interface_package, make_typestore, type_hash

# Published hashes: std_msgs/String and example_interfaces/AddTwoInts in rmw_zenoh's docs/design.md (key
# expression examples); sensor_msgs/Image in a ROS 2 Jazzy rmw_zenoh publisher's log; tf2_msgs/TFMessage and
# rcl_interfaces/Log in liveliness tokens captured from ROS 2 nodes on rmw_zenoh (/tf, /rosout of ros2cli).
KNOWN = {
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "rcl_interfaces/msg/Log": "RIHS01_e28ce254ca8abc06abf92773b74602cdbf116ed34fbaf294fb9f81da9f318eac",
}
PACKAGE_DIR = Path(__file__).resolve().parents[2] / "ros2" / "polarstripe_msgs"
ADD_TWO_INTS = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"


def test_hashes_equal_published_values():
    for typename, known in KNOWN.items():
        assert type_hash(typename) == known, typename
    store = make_typestore({"example_interfaces/srv/AddTwoInts": ("int64 a\nint64 b\n", "int64 sum\n")})
    assert store.hash_rihs01("example_interfaces/srv/AddTwoInts") == ADD_TWO_INTS


def test_standard_hashes_equal_ros2_pyterfaces():
    from ros2_pyterfaces.core import hash_rihs01
    from ros2_pyterfaces.core.geometry_msgs import msg as geometry
    from ros2_pyterfaces.core.rcl_interfaces import msg as rcl
    from ros2_pyterfaces.core.sensor_msgs import msg as sensor
    from ros2_pyterfaces.core.service_msgs import msg as service

    for typename, schema in {"sensor_msgs/msg/Image": sensor.Image,
                             "sensor_msgs/msg/CameraInfo": sensor.CameraInfo,
                             "sensor_msgs/msg/JointState": sensor.JointState,
                             "rcl_interfaces/msg/Log": rcl.Log,
                             "geometry_msgs/msg/TransformStamped": geometry.TransformStamped,
                             "service_msgs/msg/ServiceEventInfo": service.ServiceEventInfo}.items():
        assert type_hash(typename) == hash_rihs01(schema), typename


def test_package_hashes_equal_the_third_party_clients(ros2_msgs_dir):
    """zenoh-ros2-sdk hashes the shipped .msg/.srv files with its own code; the bridge's keys must agree."""
    from zenoh_ros2_sdk.message_registry import MessageRegistry
    from zenoh_ros2_sdk.utils import compute_service_type_hash, get_type_hash, load_dependencies_recursive

    folder = ros2_msgs_dir
    registry = MessageRegistry(str(folder))
    for kind in RECORDS:
        t = f"polarstripe_msgs/msg/{kind}"
        text = (folder / "polarstripe_msgs" / "msg" / f"{kind}.msg").read_text()
        assert get_type_hash(t, text, load_dependencies_recursive(t, text, registry)) == type_hash(t), t
    for name in SERVICES:
        t = f"polarstripe_msgs/srv/{name}"
        request, response = (folder / "polarstripe_msgs" / "srv" / f"{name}.srv").read_text().split("---\n")
        deps = {**load_dependencies_recursive(t + "_Request", request, registry),
                **load_dependencies_recursive(t + "_Response", response, registry)}
        assert compute_service_type_hash(t, request, response, deps) == type_hash(t), t


def test_shipped_package_is_the_generated_one():
    shipped = {str(p.relative_to(PACKAGE_DIR)): p.read_text() for p in PACKAGE_DIR.rglob("*") if p.is_file()}
    assert shipped == interface_package(__version__), "run: polarstripe ros2 msgs -o ros2/polarstripe_msgs"


def test_records_carry_every_field_of_their_message():
    """A record named like a message of msgs/ has each of its fields (Heartbeat's counters as two arrays)."""
    spelled = {("Heartbeat", "counters"): ("counter_names", "counter_values")}
    checked = 0
    for cls in REGISTRY.values():
        if cls.__name__ not in RECORDS:
            continue
        record = {name for name, _ in RECORDS[cls.__name__]}
        for f in dataclasses.fields(cls):
            if f.name != "header":
                assert set(spelled.get((cls.__name__, f.name), (f.name,))) <= record, (cls.__name__, f.name)
        checked += 1
    assert checked == 6
    request = SERVICES["StartScan"][0].split()
    assert request[1::2] == [f.name for f in dataclasses.fields(ScanRequest) if f.name != "header"]


def test_cli_writes_the_package_and_refuses_a_foreign_folder(tmp_path, capsys):
    from polarstripe.tools.cli import main

    out = tmp_path / "polarstripe_msgs"
    (out / "msg").mkdir(parents=True)
    (out / "msg" / "Gone.msg").write_text("int32 x\n")
    assert main(["ros2", "msgs", "-o", str(out)]) == 0
    written = {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()}
    assert written == set(interface_package(__version__))
    (out / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main(["ros2", "msgs", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("polarstripe ros2: error:")
    assert "not polarstripe_msgs'" in err


@pytest.mark.parametrize("typename", ["sensor_msgs/msg/Image", "polarstripe_msgs/srv/StartScan"])
def test_hash_is_stable_text(typename):
    assert type_hash(typename).startswith("RIHS01_") and len(type_hash(typename)) == 7 + 64


def test_depth_map_is_an_image_and_a_point_cloud():
    """A DepthMap's views in ROS 2 types, read back by rosbags with its own Jazzy definitions."""
    import numpy as np
    from polarstripe.msgs import DepthMap, Header
    from polarstripe.nodes.rig_views import RigViews
    from polarstripe.nodes.ros2_schemas import Ros2Encoder
    from rosbags.typesys import Stores, get_typestore

    depth = np.full((4, 5), np.nan, np.float32)
    depth[1, 2], depth[3, 0] = 0.31, 0.29
    points = np.array([[0.01, -0.02, 0.31], [-0.1, 0.05, 0.29]], np.float32)
    msg = DepthMap(depth_m=depth, points_m=points, method="stripes", scan_id=3,
                   header=Header(stamp_ns=2_000_000_007, frame_id="camera"))
    views = RigViews(None).views("/rig/compositor/depth", 2_000_000_007, msg)
    encoded = {e.topic: e for e in map(Ros2Encoder().encode, views)}
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    cloud = encoded["/rig/compositor/depth/points"]
    assert cloud.msgtype == "sensor_msgs/msg/PointCloud2"
    c = jazzy.deserialize_cdr(b"".join(cloud.parts), cloud.msgtype)
    assert (c.height, c.width, c.point_step, c.row_step) == (1, 2, 12, 24)
    assert c.is_dense and not c.is_bigendian
    assert [(f.name, f.offset, f.datatype, f.count) for f in c.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)]  # 7: PointField.FLOAT32
    assert np.array_equal(np.frombuffer(bytes(c.data), "<f4").reshape(-1, 3), points)
    assert (c.header.frame_id, c.header.stamp.sec, c.header.stamp.nanosec) == ("camera", 2, 7)
    image = encoded["/rig/compositor/depth/image"]
    i = jazzy.deserialize_cdr(b"".join(bytes(p) for p in image.parts), image.msgtype)
    assert (i.encoding, i.width, i.height) == ("32FC1", 5, 4)
    assert np.array_equal(np.frombuffer(bytes(i.data), "<f4").reshape(4, 5), depth, equal_nan=True)
    assert encoded["/rig/compositor/depth"].msgtype == "polarstripe_msgs/msg/Packed"  # the whole message too
    no_points = DepthMap(depth_m=depth, points_m=None, method="stripes")
    assert [v.topic for v in RigViews(None).views("/d", 1, no_points)] == ["/d/image", "/d"]
