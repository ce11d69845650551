"""A ROS 2 program we did not write (zenoh-ros2-sdk) driving the simulated rig of ``launch/sim.toml
sequence=false ros2=true``, run by tests/launch/test_ros2_launch.py as ``python ros2_drive_client.py PORT
MSGS_DIR``: it calls /rig/emitter/start_scan (flood) until the rig answers, and again while no composite's
metrics arrive on /rig/compositor/composite/metrics (a scan that started before the compositor was up has
none); prints one JSON line per call and the metrics it got."""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np
from zenoh_ros2_sdk import ROS2ServiceClient, ROS2Subscriber, get_registry

port, folder = int(sys.argv[1]), sys.argv[2]
get_registry(folder)
metrics: list = []
sub = ROS2Subscriber("/rig/compositor/composite/metrics", "polarstripe_msgs/msg/CompositeMetrics",
                     lambda m: metrics.append({"method": m.method, "scan_id": int(m.scan_id),
                                               "contrast": float(m.contrast)}), router_port=port)
client = ROS2ServiceClient("/rig/emitter/start_scan", "polarstripe_msgs/srv/StartScan", router_port=port,
                           timeout=20.0)
deadline = time.monotonic() + 200
while not metrics and time.monotonic() < deadline:
    r = client.call(method="flood", stripes=0, analyzer_deg=np.zeros(0), sheets=0)
    print(json.dumps({"call": None if r is None else {"ok": bool(r.ok), "event": r.event.event,
                                                      "scan_id": int(r.event.scan_id)}}), flush=True)
    waited = time.monotonic()
    while not metrics and time.monotonic() - waited < (30 if r is not None and r.ok else 3):
        time.sleep(0.2)
print(json.dumps({"metrics": metrics}), flush=True)
os._exit(0)  # zenoh's threads would keep the process
