"""``polarstripe camera list|grab|fake`` against Aravis's GigE Vision simulator on 127.0.0.1 (opened by
address, no broadcast): the frame written is the simulator's ramp bit-exact (tests/nodes/drivers/
test_aravis_camera.py has the closed form), and every mistake is one line."""

from __future__ import annotations

import re
import subprocess
import sys

import cv2
import numpy as np
import pytest
from polarstripe.tools.cli import main

RAMP8 = lambda fid: ((np.add.outer(np.arange(512), np.arange(512)) + fid) % 255).astype(np.uint8)  # noqa: E731


def run(*argv: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "polarstripe", "camera", *argv], capture_output=True,
                          text=True, timeout=timeout)


def test_grab_writes_the_cameras_frame(gige, tmp_path):
    out = tmp_path / "frame.png"
    proc = run("grab", f"aravis:{gige.address}", "-o", str(out), "--exposure-us", "100000", "--gain", "0",
               "--pixel-format", "Mono16", "--trigger", "software")
    assert proc.returncode == 0, proc.stderr
    said = re.search(r"512x512 Mono16 \(16 bits\), exposure 100000 µs, gain 0, frame (\d+), device time \d+",
                     proc.stdout)
    assert said, proc.stdout
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    fid = int(said.group(1))
    y, x = np.indices((512, 512))
    expected = np.clip(((256 * x + 256 * fid + 256 * y) % 65535) * 2.0, 0, 65535).astype(np.uint16)
    assert image.dtype == np.uint16 and np.array_equal(image, expected)  # 100 ms: twice the 10 ms ramp


def test_grab_in_process_mono8_npy(gige, tmp_path, capsys):
    out = tmp_path / "frame.npy"
    assert main(["camera", "grab", f"aravis:{gige.address}", "-o", str(out), "--exposure-us", "10000",
                 "--gain", "0", "--pixel-format", "Mono8"]) == 0
    fid = int(re.search(r"frame (\d+)", capsys.readouterr().out).group(1))
    assert np.array_equal(np.load(out), RAMP8(fid))


def test_list_by_address_names_the_camera(gige, capsys):
    assert main(["camera", "list", "--address", gige.address]) == 0
    assert capsys.readouterr().out.split() == ["aravis:127.0.0.1", "Aravis", "Fake,", "serial", "GV01",
                                               "(GigEVision)"]


@pytest.mark.parametrize(("argv", "text"), [
    (["--pixel-format", "Mono12"], "pixel_format Mono12 is not offered (the camera offers"),
    (["--trigger", "Line7"], "trigger source Line7 is not offered (TriggerSource: Line0, Software)"),
    (["--trigger", "Line0", "--timeout", "0.3"], "no frame within 0.3 s (no pulse on Line0?)"),
    (["--exposure-us", "2e7"], "outside the camera's 10-1e+07 µs (ExposureTimeAbs)"),
])
def test_what_the_camera_cannot_do_is_one_line(gige, tmp_path, capsys, argv, text):
    out = tmp_path / "f.png"
    assert main(["camera", "grab", f"aravis:{gige.address}", "-o", str(out), *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("polarstripe camera: error: ") and text in err and err.count("\n") == 1
    assert not out.exists()


@pytest.mark.parametrize(("argv", "text"), [
    (["grab", "aravis", "-o", "f.png"], "give BACKEND:DEVICE"),
    (["grab", "aravis:127.0.0.1", "-o", "f.jpg"], "write .png, .tif or .npy"),
    (["grab", "v4l2:/dev/video0", "-o", "f.png", "--pixel-format", "Mono8"],
     "camera backend 'v4l2': unknown option 'pixel_format'"),
    (["grab", "nikon:1", "-o", "f.png"], "unknown camera backend 'nikon'"),
    (["fake", "--address", "10.0.0.1"], "'10.0.0.1' is no loopback address"),
])
def test_mistakes_are_one_line(tmp_path, capsys, monkeypatch, argv, text):
    monkeypatch.chdir(tmp_path)
    assert main(["camera", *argv]) == 2
    err = capsys.readouterr().err
    assert text in err and err.count("\n") == 1


def test_help_names_the_actions():
    proc = run("--help")
    assert proc.returncode == 0 and all(a in proc.stdout for a in ("list", "grab", "fake"))
    proc = run("grab", "--help")
    assert proc.returncode == 0 and "--exposure-us" in proc.stdout and "--pixel-format" in proc.stdout
