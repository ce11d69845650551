"""launch/lab_rig.toml and launch/rov.toml: both pass ``polarstripe launch FILE --dry-run`` on a machine
without their hardware, and the ROV's tcp link is CURVE-encrypted and authenticated (per-host keys, an
allow-list) when its nodes really run.

The CURVE test runs rov.toml's own [launch], [launch.env] and [args] with only its polarizer node (the other
nodes need a camera, a serial laser controller and can0): with no CAN interface the polarizer keeps
publishing its "not connected" fault, which is what a topside client listens to here.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zmq
import zmq.auth
from polarstripe.msgs import PolarizerState
from polarstripe.runtime.bus import BusTimeout, CurveKeys, Subscriber
from polarstripe.runtime.launch_file import load_launch
from polarstripe.tools.cli import main as cli

LAUNCH = Path(__file__).resolve().parents[2] / "launch"


def _dry_run(capsys, name: str, *overrides: str) -> dict:
    """``polarstripe launch FILE --dry-run`` in this process (the interpreter's start-up and the nodes'
    imports, ~2.5 s of CPU a run, paid once)."""
    assert cli(["launch", str(LAUNCH / name), "--dry-run", *overrides]) == 0, capsys.readouterr().err
    return json.loads(capsys.readouterr().out)


def test_lab_rig_dry_run(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("POLARSTRIPE_RUNS", str(tmp_path))
    graph = _dry_run(capsys, "lab_rig.toml", "chart_bright=200,260,300,900", "chart_dark=260,320,300,900")
    nodes = graph["nodes"]
    assert set(nodes) == {"polarizer", "grabber", "emitter", "compositor", "planner", "sequencer"}
    pol = nodes["polarizer"]["params"]
    assert pol["stage"] == "cia402"
    assert pol["stage_options"]["interface"] == "socketcan" and pol["stage_options"]["channel"] == "can0"
    assert nodes["grabber"]["params"]["camera"] == "v4l2"
    assert nodes["emitter"]["params"]["display"] == "window"
    assert nodes["compositor"]["params"]["chart_bright_roi"] == [200, 260, 300, 900]
    assert all(n["pub"].startswith("ipc://") for n in nodes.values())
    assert "/rig/polarizer/calibrate" in graph["services"]


def test_rov_dry_run(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("POLARSTRIPE_RUNS", str(tmp_path))
    graph = _dry_run(capsys, "rov.toml")
    nodes = graph["nodes"]
    assert set(nodes) == {"polarizer", "grabber", "emitter", "compositor", "planner"}  # no survey
    for n in nodes.values():
        assert n["pub"].startswith("tcp://127.0.0.1:") and n["srv"].startswith("tcp://127.0.0.1:")
    assert nodes["emitter"]["params"]["display"] == "serial"
    assert "sequencer" in _dry_run(capsys, "rov.toml", "survey=true")["nodes"]
    spec = load_launch(LAUNCH / "rov.toml", {"keys_dir": "/k"})
    assert spec.env["POLARSTRIPE_CURVE_KEYS"] == "/k/vehicle.key_secret"  # every node reads its keys there
    assert spec.env["POLARSTRIPE_CURVE_ALLOW"] == "/k/allowed"  # and answers only these clients


@pytest.fixture
def rov_polarizer_only(tmp_path):
    text = (LAUNCH / "rov.toml").read_text()
    head, *blocks = text.split("[[node]]")
    polarizer = next(b for b in blocks if 'name = "polarizer"' in b)
    path = tmp_path / "rov_polarizer.toml"
    path.write_text(head + "[[node]]" + polarizer)
    keys = tmp_path / "keys"  # the vehicle's pair, topside's public cert on its allow-list
    (keys / "allowed").mkdir(parents=True)
    vehicle_public, vehicle_secret = zmq.auth.create_certificates(keys, "vehicle")
    os.chmod(vehicle_secret, 0o600)
    topside_public, topside_secret = zmq.auth.create_certificates(tmp_path, "topside")
    os.chmod(topside_secret, 0o600)
    os.replace(topside_public, keys / "allowed" / "topside.key")
    public = zmq.auth.load_certificate(vehicle_public)[0]
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")}
    proc = subprocess.Popen([sys.executable, "-m", "polarstripe", "launch", str(path), f"keys_dir={keys}"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        graph_file = None
        while graph_file is None and time.monotonic() < deadline:
            found = list((tmp_path / "runs").glob("*/graph.json"))
            graph_file = found[0] if found else None
            time.sleep(0.1)
        assert graph_file is not None, "no graph.json"
        yield json.loads(graph_file.read_text()), public, graph_file, Path(topside_secret)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_rov_link_is_curve_encrypted_and_authenticated(rov_polarizer_only):
    graph, public, _, topside_secret = rov_polarizer_only
    endpoint = graph["nodes"]["polarizer"]["pub"]
    assert endpoint.startswith("tcp://")
    t_public, t_secret = zmq.auth.load_certificate(topside_secret)
    with_key = Subscriber([endpoint], "/rov/polarizer/state", PolarizerState,
                          curve=CurveKeys(t_public, t_secret, server_public=public))
    stranger = Subscriber([endpoint], "/rov/polarizer/state", PolarizerState,
                          curve=CurveKeys(server_public=public))  # knows the server's key, not allowed
    plain = Subscriber([endpoint], "/rov/polarizer/state", PolarizerState)
    try:
        state = with_key.recv(timeout_s=25.0)  # the node needs a few seconds to start
        assert "not connected" in state.fault  # no can0 here: a published fault, not an angle
        with pytest.raises(BusTimeout):
            plain.recv(timeout_s=1.0)  # a client without the server's key hears nothing
        with pytest.raises(BusTimeout):
            stranger.recv(timeout_s=1.0)  # nor one whose key is not on the vehicle's allow-list
    finally:
        with_key.socket.close(0)
        stranger.socket.close(0)
        plain.socket.close(0)


def test_topside_echo_with_its_own_keys(rov_polarizer_only, tmp_path):
    """The recipe of rov.toml's header: graph.json, topside's own key pair and the vehicle's public cert."""
    _, public, graph_file, topside_secret = rov_polarizer_only
    vehicle = tmp_path / "vehicle.key"
    vehicle.write_text(f'curve\n    public-key = "{public.decode()}"\n')
    env = {**os.environ, "POLARSTRIPE_CURVE_KEYS": str(topside_secret),
           "POLARSTRIPE_CURVE_SERVER": str(vehicle)}
    out = subprocess.run([sys.executable, "-m", "polarstripe", "topic", "--graph", str(graph_file), "echo",
                          "/rov/polarizer/state", "-n", "1", "--timeout", "25"],
                         env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "not connected" in out.stdout
