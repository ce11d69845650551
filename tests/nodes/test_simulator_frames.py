"""The simulator node's plain functions: the resolution param, the model's resolution per pattern, the resize
to the camera, and the auto-exposure factor against hand-computed numbers."""

import numpy as np
import pytest
from polarstripe.nodes.simulator_frames import exposure_factor, model_scene, parse_resolution, to_camera
from polarstripe.sim.scene import load_scene


def test_parse_resolution():
    assert parse_resolution("") is None
    assert parse_resolution("64x48") == (64, 48)
    with pytest.raises(ValueError, match="need at least 2x2"):
        parse_resolution("1x5")
    with pytest.raises(ValueError, match="WxH"):
        parse_resolution("big")


def test_model_scene_divides_the_camera_and_keeps_checkers_finer():
    scene = load_scene(None)
    scene = scene.replace(camera=scene.camera.replace(resolution=(100, 50)))
    assert model_scene(scene, "stripe:1/4", 1) is scene
    assert model_scene(scene, "stripe:1/4", 3).camera.resolution == (33, 17)  # round(100/3), round(50/3)
    assert model_scene(scene, "checker:8:0", 4).camera.resolution == (50, 25)  # checkers at twice: 1/2
    assert model_scene(scene, "checker:8:0", 3) is scene  # 3 // 2 = 1
    assert model_scene(scene, "flood", 80).camera.resolution == (2, 2)  # never below 2x2


def test_to_camera_keeps_a_fitting_image_and_resizes_another():
    img = np.arange(12.0).reshape(3, 4)
    assert to_camera(img, (4, 3)) is img  # (w, h)
    big = to_camera(np.full((2, 3), 7.5), (6, 4))
    assert big.shape == (4, 6) and np.all(big == 7.5)  # bilinear: a constant stays constant


def test_exposure_factor_puts_the_percentile_at_85_percent_of_the_range():
    cam = load_scene(None).camera.replace(dark_current_e_s=0.0)  # 12 bit, offset 64, 12 e-/DN, 50 000 e-
    limit = 0.85 * min(4095 - 64, 50000 / 12)  # the ADC is the smaller range here: 3426.35 DN
    radiance = np.ones((10, 100))
    radiance[0, 0] = 1e6  # one hot pixel: above the 99.5th percentile, not counted
    e_map = np.full((10, 100), 2 * limit * 12)  # the rest would sit at twice the limit
    assert exposure_factor(radiance, e_map, cam) == pytest.approx(0.5, rel=1e-12)
    assert exposure_factor(radiance, e_map / 4, cam) == 1.0  # half the limit: left alone
    wells = cam.replace(gain_e_per_dn=20.0)  # now the full well is: 50 000 / 20 = 2500 DN < 4031
    e_map = np.full((10, 100), 2 * 0.85 * 2500 * 20)
    assert exposure_factor(radiance, e_map, wells) == pytest.approx(0.5, rel=1e-12)
