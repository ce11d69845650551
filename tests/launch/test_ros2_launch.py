"""``polarstripe launch launch/sim.toml ros2=true`` against a Zenoh router on loopback: the launch's ``ros2``
node is wired from the launch args (default run, the files read), and, with ``--long``, a whole small demo
seen from a Zenoh client as ROS 2 sees it (the node's liveliness tokens and a composite image decoded by
rosbags from its rmw_zenoh key), and the idle rig (``sequence=false``) driven by a ROS 2 client we did not
write (zenoh-ros2-sdk: start_scan, then the composite's metrics)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

ROOT = Path(__file__).resolve().parents[2]


def test_ros2_args_wire_the_bridge(tmp_path):
    from polarstripe.runtime.launch_file import load_launch

    off = load_launch(ROOT / "launch" / "sim.toml", run_dir=tmp_path / "a")
    assert "ros2" not in {n.name for n in off.nodes}
    on = load_launch(ROOT / "launch" / "sim.toml", {"ros2": "true", "ros2_endpoint": "tcp/10.0.0.2:7448",
                                                   "ros2_domain": "7"}, run_dir=tmp_path / "b")
    node = next(n for n in on.nodes if n.name == "ros2")
    assert node.module == "polarstripe.nodes.ros2_bridge:Ros2Bridge"
    assert node.params == {"endpoint": "tcp/10.0.0.2:7448", "domain": 7}
    assert "sequencer" in {n.name for n in on.nodes}
    idle = load_launch(ROOT / "launch" / "sim.toml", {"ros2": "true", "sequence": "false"},
                       run_dir=tmp_path / "d")
    names = {n.name for n in idle.nodes}
    assert {"ros2", "emitter", "compositor"} <= names and "sequencer" not in names
    rov = load_launch(ROOT / "launch" / "rov.toml", {"ros2": "true", "keys_dir": "/k"},
                      run_dir=tmp_path / "c")
    params = next(n for n in rov.nodes if n.name == "ros2").params
    assert params["endpoint"].startswith("tls/") and params["tls_ca"] == "/k/tls/ca.pem"
    assert (params["tls_cert"], params["tls_key"]) == ("/k/tls/vehicle.pem", "/k/tls/vehicle.key")


def _router(port: int):
    c = zenoh.Config()
    for k, v in {"mode": "router", "listen/endpoints": [f"tcp/127.0.0.1:{port}"], "connect/endpoints": [],
                 "scouting/multicast/enabled": False, "scouting/gossip/enabled": False}.items():
        c.insert_json5(k, json.dumps(v))
    return zenoh.open(c)


@pytest.mark.long
def test_sim_launch_shows_a_composite_to_ros2(tmp_path):
    from rosbags.typesys import Stores, get_typestore

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    router = _router(port)
    c = zenoh.Config()
    for k, v in {"mode": "client", "connect/endpoints": [f"tcp/127.0.0.1:{port}"],
                 "scouting/multicast/enabled": False, "scouting/gossip/enabled": False}.items():
        c.insert_json5(k, json.dumps(v))
    viewer = zenoh.open(c)
    tokens, images = set(), {}
    viewer.liveliness().declare_subscriber("@ros2_lv/0/**", lambda s: tokens.add(str(s.key_expr)))
    viewer.declare_subscriber("0/rig/compositor/composite/*/sensor_msgs::msg::dds_::Image_/*",
                              lambda s: images.setdefault(str(s.key_expr), s.payload.to_bytes()))
    can = tempfile.mkdtemp(prefix="ps-can-", dir="/tmp")
    try:
        r = subprocess.run(
            [sys.executable, "-m", "polarstripe", "launch", str(ROOT / "launch" / "sim.toml"), "--once",
             f"out={tmp_path / 'out'}", "resolution=96x72", "stripes=8", f"can=ipc://{can}/bus", "ros2=true",
             f"ros2_endpoint=tcp/127.0.0.1:{port}"],
            cwd=tmp_path, env={**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")}, capture_output=True,
            text=True, timeout=300)
        time.sleep(0.2)
    finally:
        shutil.rmtree(can, ignore_errors=True)
        viewer.close()
        router.close()
    logs = {p.stem: p.read_text() for p in (tmp_path / "runs").glob("*/logs/*.log")}
    assert "ROS 2 (rmw_zenoh) via" in logs.get("ros2", ""), (r.stderr[-2000:], logs.get("ros2", "")[-2000:])
    assert any(t.endswith("/NN/%/%rig/polarstripe") for t in tokens), sorted(tokens)
    key = next((k for k in images if k.startswith("0/rig/compositor/composite/composite/")), None)
    assert key, sorted(images)
    m = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(images[key], "sensor_msgs/msg/Image")
    assert (m.width, m.height, m.encoding) == (96, 72, "32FC1")
    pixels = np.frombuffer(bytes(m.data), "<f4").reshape(72, 96)
    assert np.isfinite(pixels).all() and pixels.max() > 0


@pytest.mark.long
def test_idle_sim_rig_scans_when_ros2_asks(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    msgs = tmp_path / "msgs"
    shutil.copytree(ROOT / "tests" / "data" / "ros2_msgs", msgs)
    for kind in ("msg", "srv"):
        shutil.copytree(ROOT / "ros2" / "polarstripe_msgs" / kind, msgs / "polarstripe_msgs" / kind)
    config = tmp_path / "session.json5"
    no_scouting = {"multicast": {"enabled": False}, "gossip": {"enabled": False}}
    config.write_text(json.dumps({"mode": "peer", "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
                                  "scouting": no_scouting}))
    router = _router(port)
    can = tempfile.mkdtemp(prefix="ps-can-", dir="/tmp")
    launch = subprocess.Popen(
        [sys.executable, "-m", "polarstripe", "launch", str(ROOT / "launch" / "sim.toml"),
         f"out={tmp_path / 'out'}", "resolution=96x72", f"can=ipc://{can}/bus", "ros2=true",
         f"ros2_endpoint=tcp/127.0.0.1:{port}", "sequence=false"],
        cwd=tmp_path, env={**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")}, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True)
    try:
        script = ROOT / "tests" / "launch" / "ros2_drive_client.py"
        client = subprocess.run([sys.executable, str(script), str(port), str(msgs)],
                                env={**os.environ, "ZENOH_SESSION_CONFIG_URI": str(config)},
                                capture_output=True, text=True, timeout=260)
    finally:
        launch.send_signal(signal.SIGINT)
        try:
            out, _ = launch.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            launch.kill()
            out, _ = launch.communicate()
        shutil.rmtree(can, ignore_errors=True)
        router.close()
    lines = [json.loads(x) for x in client.stdout.splitlines() if x.startswith("{")]
    calls = [x["call"] for x in lines if "call" in x]
    got = next((x["metrics"] for x in lines if "metrics" in x), [])
    assert got, (lines, client.stderr[-1500:], out[-2500:])
    started = [c for c in calls if c and c["ok"]]
    assert started and all(c["event"] == "start" for c in started)
    assert got[0]["method"] == "flood" and got[0]["scan_id"] in {c["scan_id"] for c in started}
    assert launch.returncode == 130 and "SIGINT: stopping" in out  # it ran until told to stop
