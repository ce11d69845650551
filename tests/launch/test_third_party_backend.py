"""A backend from another distribution: a camera registered through a real ``polarstripe.drivers`` entry point
(a temporary ``.dist-info`` on the path, as pip would install it) runs in a launch with the options the launch
file gives it; a wrong option key or backend name is refused in one line before anything starts."""

import json
import os
import subprocess
import sys

import pytest

ACME = '''
"""A third party's camera: a constant image whose level and size are its own options."""
import numpy as np
from polarstripe.msgs import Ack, Frame, FrameRequest
from polarstripe.nodes.drivers.backend import BackendOptions
from polarstripe.nodes.drivers.camera import Camera
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams


class AcmeCamera(Camera):
    class Options(BackendOptions):
        serial: str              # required
        level: int = 0
        width: int = 4

    def __init__(self, serial, *, level=0, width=4):
        super().__init__(f"acme {serial}", exposure_s=0.01, gain=1.0, bit_depth=12)
        self.level, self.width = level, width

    def _grab(self):
        return np.full((3, self.width), self.level, np.uint16), {}


class Probe(Node):
    """Triggers one frame, writes what arrived to ``out``, and ends the launch."""

    class Params(NodeParams):
        out: str = ""

    SUBSCRIBES = {"camera/frame": Frame}

    def setup(self):
        self.frames = []
        self.subscribe("camera/frame", self.frames.append, mode="all")
        self.trigger = self.client("camera/trigger", FrameRequest, Ack, timeout_s=5.0)
        self.every(0.2, self.try_once, name="probe")

    def try_once(self):
        if self.frames:
            f = self.frames[0]
            with open(self.params.out, "w") as fh:
                fh.write(f"{f.image.shape[1]} {int(f.image.max())} {f.exposure_s}")
            self.stop("probe done")
            return
        try:
            self.trigger.call(FrameRequest(scan_id=1, step=0, pattern="flood"))
        except Exception:
            pass  # the grabber is not up yet: try again
'''

LAUNCH = """
[launch]
name = "acme"
namespace = "/rig"
[[node]]
name = "grabber"
module = "polarstripe.nodes.grabber"
params = {{ camera = "{camera}", camera_options = {options}, exposure_s = 0.02 }}
[[node]]
name = "probe"
module = "acme_camera:Probe"
params = {{ out = "{out}" }}
required = true
"""


@pytest.fixture
def site(tmp_path):
    """A folder on the path holding the module and its distribution's metadata (an entry point)."""
    site = tmp_path / "site"
    (site / "acme_camera-1.0.dist-info").mkdir(parents=True)
    (site / "acme_camera.py").write_text(ACME)
    (site / "acme_camera-1.0.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: acme-camera\nVersion: 1.0\n")
    (site / "acme_camera-1.0.dist-info" / "entry_points.txt").write_text(
        "[polarstripe.drivers]\ncamera.acme = acme_camera:AcmeCamera\n")
    return site


def _launch(tmp_path, site, camera, options, *extra):
    out = tmp_path / "probe.txt"
    f = tmp_path / "acme.toml"
    f.write_text(LAUNCH.format(camera=camera, options=options, out=out))
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs"),
           "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "polarstripe", "launch", str(f), *extra], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=90)
    return proc, out


@pytest.mark.slow
def test_an_entry_point_camera_gets_its_options_in_a_launch(tmp_path, site):
    proc, out = _launch(tmp_path, site, "acme", '{ serial = "A-17", level = 1234, width = 6 }', "--once")
    assert proc.returncode == 0, proc.stderr
    width, level, exposure = out.read_text().split()
    assert (int(width), int(level)) == (6, 1234)  # the options reached the backend
    assert float(exposure) == 0.02  # the node's exposure went through the camera role


@pytest.mark.parametrize(("camera", "options", "text"), [
    ("acme", '{ serial = "A-17", levle = 3 }', "camera backend 'acme': unknown option 'levle' (known: level, "
                                               "serial, width)"),
    ("acme", "{ level = 3 }", "camera backend 'acme': missing option 'serial'"),
    ("acme", '{ serial = "A-17", level = "bright" }', "camera backend 'acme': option 'level': bad value"),
    ("acmee", "{}",
     "unknown camera backend 'acmee' (choose from acme, aravis, file, sim, sim_polarization, v4l2)"),
])
def test_a_bad_option_or_backend_is_one_line_before_anything_starts(tmp_path, site, camera, options, text):
    proc, out = _launch(tmp_path, site, camera, options, "--dry-run")
    assert proc.returncode == 2, proc.stderr
    assert text in proc.stderr and "node 'grabber'" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr
    assert not out.exists()


def test_dry_run_records_the_options_in_the_graph(tmp_path, site):
    proc, _ = _launch(tmp_path, site, "acme", '{ serial = "A-17" }', "--dry-run")
    assert proc.returncode == 0, proc.stderr
    graph = json.loads(proc.stdout)
    assert graph["nodes"]["grabber"]["params"]["camera_options"] == {"serial": "A-17"}
