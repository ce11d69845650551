"""The simulator's medium override (params medium_sigma_t, medium_g): the estimator's truth in a launch."""

import pytest
from polarstripe.nodes.simulator import Simulator
from polarstripe.nodes.simulator_frames import rig_scene
from polarstripe.runtime.params import ParamError
from polarstripe.runtime.testing import NodeHarness
from polarstripe.sim.scene import load_scene


def test_override_changes_sigma_t_and_phase_only():
    tank = load_scene(None)
    sc = rig_scene("", "64x48", None, 3.0, 0.9)
    assert sc.medium.sigma_t == 3.0 and sc.medium.phase.model == "tthg" and sc.medium.phase.g == 0.9
    assert sc.medium.albedo == tank.medium.albedo and sc.medium.dop == tank.medium.dop
    assert sc.camera.resolution == (64, 48)
    assert rig_scene("", "", None).medium == tank.medium  # no override: the scene's


def test_simulator_node_takes_the_override_and_refuses_bad_values():
    h = NodeHarness(Simulator, name="simulator", params={"resolution": "32x24", "medium_sigma_t": "1.5",
                                                         "medium_g": "0.7"})
    assert h.node.scene.medium.sigma_t == 1.5 and h.node.scene.medium.phase.g == 0.7
    h.stop()
    with pytest.raises(ParamError, match="medium_g must be in"):
        NodeHarness(Simulator, name="simulator", params={"medium_g": "1.2"})
    with pytest.raises(ParamError, match="medium_sigma_t must be >= 0"):
        NodeHarness(Simulator, name="simulator", params={"medium_sigma_t": "-1"})


def test_simulator_and_planner_take_the_light():
    """Param light: circular mounts the quarter-wave plates on the simulator's and the planner's scene
    (sim.scene.with_light); a light that is neither is a param error."""
    from polarstripe.nodes.planner import Planner

    h = NodeHarness(Simulator, name="simulator", params={"resolution": "32x24", "light": "circular"})
    assert h.node.scene.projector.polarization.quarter_wave_deg == 45.0
    assert h.node.scene.camera.polarizer.quarter_wave_deg == 45.0
    h.stop()
    h = NodeHarness(Planner, name="planner", params={"resolution": "32x24", "light": "circular",
                                                     "publish_on_start": False, "separations": 2,
                                                     "modality": "flood"})
    assert h.node.scene.camera.polarizer.quarter_wave_deg == 45.0
    h.stop()
    with pytest.raises(ParamError, match="light"):
        NodeHarness(Simulator, name="simulator", params={"light": "elliptic"})
