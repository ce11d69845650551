"""launch/lab_rig.toml with ``camera=aravis``: the rig's own grabber node (its [launch], [args] and grabber
block, as shipped) opens Aravis's GigE Vision simulator on 127.0.0.1 by address and publishes a software-
triggered frame; a probe node takes the other nodes' place (they need can0 and a projector)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

LAB_RIG = Path(__file__).resolve().parents[2] / "launch" / "lab_rig.toml"

PROBE = '''
"""Triggers one frame, saves it with what came with it, and ends the launch."""
import json
import numpy as np
from polarstripe.msgs import Ack, Frame, FrameRequest
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams


class Probe(Node):
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
            np.save(self.params.out + ".npy", f.image)
            with open(self.params.out + ".json", "w") as fh:
                json.dump({"exposure_s": f.exposure_s, "gain": f.gain, "bit_depth": f.bit_depth,
                           "pattern": f.pattern}, fh)
            self.stop("probe done")
            return
        try:
            self.trigger.call(FrameRequest(scan_id=1, step=0, pattern="flood"))
        except Exception:
            pass  # the grabber is not up yet: try again
'''


@pytest.mark.slow
def test_the_lab_rigs_grabber_takes_frames_from_a_gige_vision_camera(gige, tmp_path):
    head, *blocks = LAB_RIG.read_text().split("[[node]]")
    grabber = next(b for b in blocks if 'name = "grabber"' in b)
    probe_block = (f'\nname = "probe"\nmodule = "probe_node:Probe"\nparams = {{ out = "{tmp_path / "got"}" }}'
                   '\nrequired = true\n')
    (tmp_path / "rig.toml").write_text(head + "[[node]]" + grabber + "[[node]]" + probe_block)
    (tmp_path / "probe_node.py").write_text(PROBE)
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs"),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "polarstripe", "launch", str(tmp_path / "rig.toml"),
                           "--once", "camera=aravis", f"camera_device={gige.address}", "width=640",
                           "height=480", "exposure_s=0.1", "gain=0"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=90)
    assert proc.returncode == 0, proc.stderr[-2000:]
    image = np.load(tmp_path / "got.npy")
    meta = json.loads((tmp_path / "got.json").read_text())
    assert image.shape == (480, 640) and image.dtype == np.uint16  # the launch's size, Mono16 chosen
    assert meta == {"exposure_s": 0.1, "gain": 0.0, "bit_depth": 16, "pattern": "flood"}
    # Aravis's simulator ramp at 100 ms (twice the 10 ms one), for the one frame id that fits
    # (tests/nodes/drivers/test_aravis_camera.py)
    fid = np.arange(1, 65536)[:, None]
    x = np.arange(8)[None, :]
    candidates = np.clip(((256 * x + 256 * fid) % 65535) * 2.0, 0, 65535).astype(np.uint16)
    (hits,) = np.nonzero((candidates == image[0, :8]).all(axis=1))
    y, xx = np.indices(image.shape)
    assert any(np.array_equal(image, np.clip(((256 * xx + 256 * int(f + 1) + 256 * y) % 65535) * 2.0, 0,
                                             65535).astype(np.uint16)) for f in hits)
