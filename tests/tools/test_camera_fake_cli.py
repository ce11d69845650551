"""``polarstripe camera fake``: Aravis's GigE Vision simulator as a process, found at its address by the
backend, dropping packets when asked, ended by Ctrl-C with status 0."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest
from polarstripe.nodes.drivers.errors import FrameDropped
from polarstripe.nodes.drivers.registry import open_backend


@pytest.fixture
def fake_process(gige_lock):
    procs = []

    def start(*argv):
        proc = subprocess.Popen([sys.executable, "-m", "polarstripe", "camera", "fake", *argv],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs.append(proc)
        line = proc.stdout.readline()
        assert "GigE Vision fake camera (Aravis Fake GV01) at 127.0.0.1" in line, proc.stderr.read()
        return proc

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_the_fake_is_a_camera_until_interrupted(fake_process):
    proc = fake_process()
    with open_backend("camera", "aravis", {"device": "127.0.0.1", "pixel_format": "Mono8"}) as cam:
        frame = cam.grab(2.0)
    assert frame.image.shape == (512, 512) and frame.metadata["frame_id"] > 0
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=10) == 0 and proc.stderr.read() == ""


def test_the_fake_drops_packets_when_asked(fake_process):
    fake_process("--lost-ratio", "0.5")
    with open_backend("camera", "aravis", {"device": "127.0.0.1", "pixel_format": "Mono8"}) as cam:
        with pytest.raises(FrameDropped, match="dropped, incomplete"):
            cam.grab(2.0)
        assert cam.frames_dropped == 1
