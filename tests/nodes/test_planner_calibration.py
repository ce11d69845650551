"""The planner's ``calibration`` param: the real rig's pinholes from a calibration file; another rig size is
one error naming the node and the param."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.imaging.calibration import save
from polarstripe.nodes.planner import Planner
from polarstripe.runtime.testing import NodeHarness
from polarstripe.sim.depth_truth import rig_geometry
from polarstripe.sim.scene import Scene, SceneError, with_separation

FAST = {"fidelity": "preview", "separations": 4, "d_min_m": 0.05, "d_max_m": 0.45, "publish_on_start": False}


def rig_file(tmp_path) -> tuple[str, Scene]:
    s = Scene()
    rig = with_separation(s.replace(projector=s.projector.replace(fov_deg=45.0)), 0.12)
    path = str(tmp_path / "rig.yaml")
    save(path, {**rig_geometry(rig), "dist_proj": np.zeros(5)})
    return path, rig


def test_planner_takes_the_rigs_pinholes_from_the_file(tmp_path):
    path, rig = rig_file(tmp_path)
    h = NodeHarness(Planner, name="planner", params={**FAST, "calibration": path, "resolution": "160x120"})
    scene = h.node.scene
    assert scene.camera.resolution == (160, 120)  # the 640x480 calibration binned by 4
    assert scene.projector.fov_deg == pytest.approx(45.0)
    assert np.allclose(scene.projector.position, rig.projector.position, atol=1e-9)
    assert h.node.plan.separation_m > 0


def test_another_rig_size_is_one_error_naming_the_param(tmp_path):
    path, _ = rig_file(tmp_path)
    with pytest.raises(SceneError, match="param 'calibration'.*640x480 camera; the rig's is 300x200"):
        NodeHarness(Planner, name="planner", params={**FAST, "calibration": path, "resolution": "300x200"})
