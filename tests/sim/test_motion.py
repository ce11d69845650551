"""The rig moving during a scan (sim/motion.py): capture times and poses against arithmetic written out here,
a rig at rest leaves the scene as it is, and a moved rig shifts an object's image by the pinhole's f·Δ/Z."""

import math

import numpy as np
import pytest
from polarstripe.sim.motion import RigMotion, capture_times, moved, rig_axes
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import Camera, Medium, PlaneObject, Projector, Scene, SceneError, load_scene


def test_capture_times_are_frame_periods_plus_the_stage_move():
    # 3 frames at 10 deg, the stage turns 90 deg at 200 deg/s and settles 0.02 s, 3 frames at 100 deg
    t = capture_times(3, [10.0, 100.0], fps=30.0, deg_s=200.0, settle_s=0.02)
    move = 90.0 / 200.0 + 0.02
    expect = [0, 1 / 30, 2 / 30, 3 / 30 + move, 4 / 30 + move, 5 / 30 + move]
    np.testing.assert_allclose(t, expect, rtol=1e-15)
    # one pass (a polarization camera, or no analyzer): the frame periods alone
    np.testing.assert_allclose(capture_times(4, [], 25.0, 200.0, 0.02), [0, 0.04, 0.08, 0.12], rtol=1e-15)


def test_the_pose_at_frame_i_is_the_start_plus_v_t_i():
    # a rig whose baseline is the world's y: rig x = +y, z = +z, so rig y = z × x = -x
    scene = Scene(projector=Projector(position=(0.0, 0.2, 0.0), look_at=(0.0, 0.0, 0.38)))
    motion = RigMotion((0.3, 0.1, -0.05), fps=20.0, stage_deg_s=100.0, stage_settle_s=0.1)
    t = motion.times(4, [0.0, 45.0])
    world_v = np.array([-0.1, 0.3, -0.05])  # 0.3 along +y, 0.1 along -x, -0.05 along +z
    t_mid = (0.0 + (7 / 20 + 45 / 100 + 0.1)) / 2
    start = np.zeros(3) - world_v * t_mid  # the camera's pose at frame 0; it passes (0, 0, 0) mid-scan
    for i in range(8):
        t_i = i / 20 + (0.55 if i >= 4 else 0.0)
        s = motion.scene_at(scene, t, i)
        np.testing.assert_allclose(s.camera.position, start + world_v * t_i, atol=1e-15)
        np.testing.assert_allclose(s.projector.position, np.array([0, 0.2, 0]) + start + world_v * t_i,
                                   atol=1e-15)
        np.testing.assert_allclose(s.medium.extent.min, np.array([-0.3, -0.3, 0.0]) + start + world_v * t_i,
                                   atol=1e-15)
        assert s.objects == scene.objects
        assert s.separation_m() == pytest.approx(0.2, abs=1e-12)


def test_rig_axes_of_the_default_tank_are_the_scenes():
    np.testing.assert_allclose(rig_axes(load_scene(None)), np.eye(3), atol=1e-15)


def test_a_rig_at_rest_is_the_scene_itself():
    scene = load_scene(None)
    rest = RigMotion((0.0, 0.0, 0.0))
    assert not rest.moving
    t = rest.times(30, [0.0, 90.0])
    assert all(rest.scene_at(scene, t, i) is scene for i in (0, 29, 59))
    # a frame the scan does not have stays at the scene's pose too
    assert RigMotion((0.1, 0, 0)).scene_at(scene, t, 60) is scene


def _clear(scene_objects, resolution=(160, 120)):
    return Scene(medium=Medium(sigma_t=0.0), camera=Camera(resolution=resolution, fov_deg=60.0),
                 objects=scene_objects)


@pytest.mark.parametrize("axis", [0, 1])
def test_a_moved_rig_shifts_the_image_by_f_delta_over_z(axis):
    # a fronto-parallel square at depth Z: translating the camera by Δ parallel to it shifts its image by
    # f·Δ/Z pixels, f = w / (2 tan(fov/2)) (the pinhole's focal length in pixels, square pixels)
    z, w = 0.3, 160
    f_px = w / (2.0 * math.tan(math.radians(30.0)))
    delta = 10.0 * z / f_px  # a shift of 10 pixels
    scene = _clear((PlaneObject(point=(0.0, 0.0, z), size=(0.1, 0.08)),))
    offset = np.zeros(3)
    offset[axis] = delta
    rest = render_components(scene, "flood", "preview", need=("D",)).object_mask
    shifted = render_components(moved(scene, offset), "flood", "preview", need=("D",)).object_mask
    rows, cols = np.nonzero(rest)
    rows2, cols2 = np.nonzero(shifted)
    # the camera's right is -x (forward z × up y) and its rows run down: moving the rig +x moves the square
    # to -x relative to it, i.e. to the image's right; moving the rig up (+y) moves it down the image
    moved_by = (cols2.mean() - cols.mean(), rows2.mean() - rows.mean())
    expect = (10.0, 0.0) if axis == 0 else (0.0, 10.0)
    np.testing.assert_allclose(moved_by, expect, atol=0.02)
    assert rest.sum() == shifted.sum()


def test_bad_motion_is_refused_by_name():
    with pytest.raises(SceneError, match="velocity_m_s must be a list of 3 numbers"):
        RigMotion((0.1, 0.0))
    with pytest.raises(SceneError, match="fps must be a positive number"):
        RigMotion(fps=0.0)
    with pytest.raises(SceneError, match="velocity_m_s\\[0\\] must be a finite number"):
        RigMotion((math.nan, 0.0, 0.0))
    with pytest.raises(SceneError, match="offset_m must be 3 finite numbers"):
        moved(load_scene(None), (0.0, 1.0))
