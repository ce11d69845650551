"""The simulator's calibration target (``target`` params, ``simulator/target``): a checkerboard the camera
finds with OpenCV's own detector, moved between seeded poses, lit by the Gray code patterns asked for."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from polarstripe.msgs import Empty
from polarstripe.msgs.rig import RenderRequest
from polarstripe.nodes.simulator import Simulator, SimulatorError
from polarstripe.runtime.testing import NodeHarness


def make(**params):
    return NodeHarness(Simulator, name="simulator", namespace="/rig",
                       params={"resolution": "160x120", "render_scale": 1, "seed": 1, "medium_sigma_t": 0.0,
                               "auto_exposure": False, **params})


def frame(h, pattern):
    return h.call("simulator/render", RenderRequest(pattern=pattern, analyzer=False)).image


def to8(img, black):
    d = img.astype(float) - black
    return np.clip(255 * d / np.percentile(d, 99.5), 0, 255).astype(np.uint8)


def test_target_steps_through_its_poses_and_the_camera_finds_the_board():
    h = make(target="5x4", target_square_m=0.02, target_poses=2, target_seed=0)
    black = frame(h, "off").astype(float)
    first = frame(h, "flood")
    ok, corners0 = cv2.findChessboardCorners(to8(first, black), (5, 4))
    assert ok and len(corners0) == 20
    replies = [h.call("simulator/target", Empty()) for _ in range(3)]
    assert all(r.ok for r in replies)
    assert [r.detail.split(":")[0] for r in replies] == ["target pose 0 of 2", "target pose 1 of 2",
                                                         "target pose 0 of 2"]
    h.call("simulator/target", Empty())  # pose 1
    moved = frame(h, "flood")
    ok, corners1 = cv2.findChessboardCorners(to8(moved, black), (5, 4))
    assert ok and np.abs(corners1 - corners0).max() > 3  # the board moved in the image


def test_gray_pattern_and_its_inverse_light_complementary_parts_of_the_board():
    h = make(target="5x4", target_square_m=0.02, target_poses=1)
    black = frame(h, "off").astype(float)
    white = frame(h, "flood").astype(float) - black
    on = frame(h, "gray:6:col:0").astype(float) - black
    off = frame(h, "gray:6:col:1").astype(float) - black
    board = white > 0.3 * np.percentile(white, 99)
    # each lit board pixel is lit by exactly one of the two: their sum is the white frame
    assert np.median(np.abs(on + off - white)[board] / white[board]) < 0.05
    assert 0.1 < np.mean((on > off)[board]) < 0.9  # bit 6 of 1024 columns splits the board


def test_no_target_and_a_bad_board_are_one_clear_error():
    h = make(resolution="32x24")
    reply = h.call("simulator/target", Empty())
    assert not reply.ok and "param 'target'" in reply.detail
    with pytest.raises(SimulatorError, match="target"):
        make(target="5by4")


def test_a_targets_white_frame_is_supersampled_and_area_averaged():
    from polarstripe.nodes.simulator_frames import WHITE_SUPERSAMPLE, model_scene, to_camera
    from polarstripe.sim.scene import Scene

    s = Scene()
    s = s.replace(camera=s.camera.replace(resolution=(40, 30)))
    assert model_scene(s, "flood", 1, target=True).camera.resolution == (120, 90)
    assert model_scene(s, "gray:3:col:0", 1, target=True).camera.resolution == (40, 30)
    assert model_scene(s, "flood", 1).camera.resolution == (40, 30)
    k = WHITE_SUPERSAMPLE
    fine = np.random.default_rng(0).random((30 * k, 40 * k))
    block_mean = fine.reshape(30, k, 40, k).mean(axis=(1, 3))
    assert np.allclose(to_camera(fine, (40, 30)), block_mean, atol=1e-12)


def test_each_pose_is_lit_to_sixty_percent_of_full_scale_in_the_murk():
    """In the murk a nearer or farther pose needs another intensity: at each pose the white frame's 99.5th
    percentile (dark offset subtracted) is 60 % of the range, as ``calibrate --sim`` lights it."""
    h = make(target="5x4", target_square_m=0.02, target_poses=2, target_seed=0, medium_sigma_t=5.0)
    full = 4095 - 64                                    # 12 bits above the dark offset of 64 DN
    levels, intensities = [], []
    for _ in range(2):
        h.call("simulator/target", Empty())            # pose 0, then pose 1
        white = frame(h, "flood").astype(float) - 64
        levels.append(np.percentile(white, 99.5) / full)
        intensities.append(h.node.scene.projector.intensity_w_sr)
    assert levels == pytest.approx([0.6, 0.6], abs=0.03)
    assert abs(intensities[1] / intensities[0] - 1) > 0.05     # the poses did need different light
