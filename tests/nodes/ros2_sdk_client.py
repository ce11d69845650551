"""A ROS 2 program we did not write: zenoh-ros2-sdk (a Python ROS 2-over-Zenoh client implementing
rmw_zenoh's formats), run by tests/nodes/test_ros2_bridge.py as ``python ros2_sdk_client.py PORT MSGS_DIR``.
It connects to the router at tcp/127.0.0.1:PORT, subscribes to the camera frame's image, camera info and
info and to the depth's point cloud, looks at the graph through the liveliness tokens, calls
/rig/emitter/start_scan and /rig/planner/plan, and prints one JSON line per finding."""

from __future__ import annotations

import hashlib
import json
import os
import sys
import threading
import time

import numpy as np

port, folder = int(sys.argv[1]), sys.argv[2]

from zenoh_ros2_sdk import (  # noqa: E402
    ROS2ServiceClient,
    ROS2Subscriber,
    ZenohSession,
    get_registry,
    get_service_names_and_types,
    get_topic_info,
    get_topic_names_and_types,
)

get_registry(folder)
session = ZenohSession.get_instance("127.0.0.1", port)
got: dict[str, dict] = {}
done = threading.Event()
TOPICS = {"/rig/camera/frame/image": "sensor_msgs/msg/Image",
          "/rig/camera/frame/camera_info": "sensor_msgs/msg/CameraInfo",
          "/rig/camera/frame/info": "polarstripe_msgs/msg/FrameInfo",
          "/rig/compositor/depth/points": "sensor_msgs/msg/PointCloud2"}


def say(**kw):
    print(json.dumps(kw), flush=True)


def on(topic):
    def cb(m):
        if topic in got:
            return
        stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        if topic.endswith("/image"):
            got[topic] = {"height": m.height, "width": m.width, "encoding": m.encoding, "step": m.step,
                          "bigendian": int(m.is_bigendian), "stamp_ns": stamp, "frame_id": m.header.frame_id,
                          "sha256": hashlib.sha256(bytes(m.data)).hexdigest()}
        elif topic.endswith("/points"):
            got[topic] = {"width": m.width, "point_step": m.point_step, "fields": [f.name for f in m.fields],
                          "sha256": hashlib.sha256(bytes(m.data)).hexdigest()}
        elif topic.endswith("/camera_info"):
            got[topic] = {"width": m.width, "height": m.height, "k": [float(x) for x in m.k],
                          "stamp_ns": stamp}
        else:
            got[topic] = {"pattern": m.pattern, "polarizer_deg": m.polarizer_deg, "seq": m.seq,
                          "stamp_ns": stamp}
        if len(got) == len(TOPICS):
            done.set()
    return cb


subs = [ROS2Subscriber(t, ty, on(t), router_port=port) for t, ty in TOPICS.items()]
say(ready=True)
if not done.wait(20):
    say(error=f"received only {sorted(got)}")
    os._exit(1)
for topic, fields in got.items():
    say(topic=topic, **fields)

time.sleep(0.2)
nodes = sorted(str(r.ok.key_expr) for r in session.liveliness.get("@ros2_lv/0/*/*/*/NN/**", timeout=1.0)
               if r.ok)
say(nodes=nodes)
say(topics=get_topic_names_and_types(router_port=port, timeout=1.0))
info = get_topic_info("/rig/camera/frame/image", router_port=port, timeout=1.0, verbose=True)
say(image_publishers=[[p.node_namespace, p.node_name, p.topic_type, p.type_hash] for p in info.publishers])
say(services=get_service_names_and_types(router_port=port, timeout=1.0))

client = ROS2ServiceClient("/rig/emitter/start_scan", "polarstripe_msgs/srv/StartScan", router_port=port,
                           timeout=10.0)
r = client.call(method="flood", stripes=0, analyzer_deg=np.array([10.0, 100.0]), sheets=0)
say(start_scan=None if r is None else {"ok": bool(r.ok), "detail": r.detail, "scan_id": int(r.event.scan_id),
                                        "event": r.event.event, "method": r.event.method,
                                        "analyzer_deg": [float(a) for a in r.event.analyzer_deg]})
r = client.call(method="", stripes=0, analyzer_deg=np.zeros(0), sheets=0)
say(refused=None if r is None else {"ok": bool(r.ok), "detail": r.detail})
plan = ROS2ServiceClient("/rig/planner/plan", "polarstripe_msgs/srv/GetPlan", router_port=port, timeout=10.0)
r = plan.call()
say(plan=None if r is None else {"ok": bool(r.ok), "modality": r.plan.modality,
                                 "separation_m": r.plan.separation_m,
                                 "curves": {c.name: [float(x) for x in c.values] for c in r.plan.curves}})
say(done=True)
sys.stdout.flush()
os._exit(0)  # zenoh's threads would keep the process
