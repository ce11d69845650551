"""Fixtures for the driver and polarizer tests: a CAN segment on ipc, a simulated CiA 402 drive in
another process; the ``--hardware`` options of the device contract suites.

Like python-can's back-to-back tests, each device contract suite (``tests/nodes/drivers/test_*_contract.py``)
runs on the simulated device always and, given ``--hardware DEVICE``, on a real one as well: a CAN channel
(``--hardware can0``: socketcan, the drive at ``--hardware-node-id``) for the CiA 402 suite, a serial port
(``--hardware /dev/ttyUSB0``: the ELLx device at ``--hardware-address``) for the ELLx suite. The options
belong to this directory: ``python -m pytest tests/nodes/drivers --hardware can0 --hardware /dev/ttyUSB0``.
"""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from polarstripe.nodes.drivers.zmqcan import ZmqCanHub


def _is_serial(device: str) -> bool:
    return device.startswith("/") or "://" in device or device.upper().startswith("COM")


def pytest_generate_tests(metafunc):
    """``can_device`` / ``ell_device``: "sim", then every ``--hardware`` device of that kind."""
    devices = metafunc.config.getoption("hardware", default=None) or []
    for name, serial_kind in (("can_device", False), ("ell_device", True)):
        if name in metafunc.fixturenames:
            targets = ["sim", *[d for d in devices if _is_serial(d) == serial_kind]]
            metafunc.parametrize(name, targets, scope="module")


@pytest.fixture
def can_channel():
    """A fresh ipc CAN channel (a short path: ipc socket paths are limited to ~107 bytes)."""
    folder = tempfile.mkdtemp(prefix="ps-can-", dir="/tmp")
    yield f"ipc://{folder}/bus"
    shutil.rmtree(folder, ignore_errors=True)


class DriveProcess:
    """``python -m polarstripe.nodes.drivers.simdrive`` with its stdin fault commands."""

    def __init__(self, channel: str, node_id: int = 5):
        self.channel, self.node_id = channel, node_id
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "polarstripe.nodes.drivers.simdrive",
                "--channel",
                channel,
                "--node-id",
                str(node_id),
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        line = self.proc.stdout.readline().strip()
        assert line == "ready", f"simulated drive did not start: {line!r}"

    def cmd(self, text: str) -> None:
        self.proc.stdin.write(text + "\n")
        self.proc.stdin.flush()
        answer = self.proc.stdout.readline().strip()
        assert answer == f"ok {text}", answer

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.write("quit\n")
            self.proc.stdin.flush()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture(scope="module")
def drive_process():
    """A hub in this process and a simulated CiA 402 drive (node 5) in another process, shared by a module."""
    folder = tempfile.mkdtemp(prefix="ps-can-", dir="/tmp")
    channel = f"ipc://{folder}/bus"
    with ZmqCanHub(channel):
        drive = DriveProcess(channel)
        yield drive
        drive.close()
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def spawn_drive():
    """Start ``DriveProcess(channel, node_id)`` objects on demand; all are stopped at teardown."""
    started = []

    def spawn(channel: str, node_id: int = 5) -> DriveProcess:
        started.append(DriveProcess(channel, node_id))
        return started[-1]

    yield spawn
    for drive in started:
        drive.close()


# ---- the ROS 2 tests (tests/nodes/test_ros2_*.py) ----------------------------------------------------------
ROS2_PACKAGE = Path(__file__).resolve().parents[2] / "ros2" / "polarstripe_msgs"


@pytest.fixture
def ros2_msgs_dir(tmp_path) -> Path:
    """The message folder the third-party client (zenoh-ros2-sdk) reads: the standard definitions of
    tests/data/ros2_msgs plus the shipped polarstripe_msgs (msg and srv)."""
    out = tmp_path / "msgs"
    shutil.copytree(ROS2_PACKAGE.parents[1] / "tests" / "data" / "ros2_msgs", out)
    for kind in ("msg", "srv"):
        shutil.copytree(ROS2_PACKAGE / kind, out / "polarstripe_msgs" / kind)
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def zenoh_router():
    """A Zenoh router (the role of ``rmw_zenohd``, with its readable admin space) on tcp/127.0.0.1:PORT only,
    no scouting of any kind; yields the port."""
    import zenoh

    port = _free_port()
    c = zenoh.Config()
    for k, v in {"mode": "router", "listen/endpoints": [f"tcp/127.0.0.1:{port}"], "connect/endpoints": [],
                 "scouting/multicast/enabled": False, "scouting/gossip/enabled": False,
                 "adminspace/enabled": True, "adminspace/permissions/read": True,
                 "scouting/delay": 0}.items():  # (a peer's wait for scouted peers: none here)
        c.insert_json5(k, json.dumps(v))
    session = zenoh.open(c)
    yield port
    session.close()
