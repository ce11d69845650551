"""Fixtures for the driver and polarizer tests: a CAN segment on ipc, a simulated CiA 402 drive in
another process.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile

import pytest
from polarstripe.nodes.drivers.zmqcan import ZmqCanHub


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
