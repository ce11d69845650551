"""The scene parts validate and normalise themselves on construction and on ``replace``."""

import math

import numpy as np
import pytest
from polarstripe.sim.scene_checks import SceneError
from polarstripe.sim.scene_parts import Box, BoxObject, Camera, Medium, Phase, PlaneObject, Projector, Scene
from polarstripe.sim.sensor import electrons_per_radiance


def test_derived_and_normalised_values():
    assert Medium(sigma_t=4.0, albedo=0.25).sigma_s == 1.0
    assert PlaneObject(normal=(0, 0, -2)).normal == (0.0, 0.0, -1.0)
    scene = Scene(projector=Projector(position=(0.3, 0.4, 0.0)))
    assert scene.separation_m() == pytest.approx(0.5, rel=1e-15)


@pytest.mark.parametrize("make, key", [
    (lambda: Phase("tthg", -0.1), "mean_cosine"),
    (lambda: Phase("hg", 1.0), "medium.phase.g"),
    (lambda: Box((0, 0, 0), (1, 1, 0)), "box.max"),
    (lambda: BoxObject(min=(0, 0, 1), max=(1, 1, 1), key="object[2]"), "object[2]"),
    (lambda: PlaneObject(normal=(0, 1, 0), up=(0, 2, 0)), "up must not be parallel"),
    (lambda: PlaneObject(texture="chart"), "size is required"),
    (lambda: Projector(black_level=1.0), "black_level"),
    (lambda: Medium().replace(albedo=math.nan), "medium.albedo"),
])
def test_invalid_parts_name_the_key(make, key):
    with pytest.raises(SceneError, match=key.replace("[", r"\[").replace("]", r"\]")):
        make()


def test_a_point_source_on_the_camera_is_refused_with_one_clear_error(tmp_path):
    """Camera and projector at one point with source_radius_m = 0: ∫ dt/t² from the camera has no bound (the
    issue's B = 5.6e198); refused by name, never rendered. A radius (the default 1 mm) or any separation is
    representable."""
    from polarstripe.sim.scene import load_scene

    with pytest.raises(SceneError, match=r"at the camera \(d_LC = 0 m\) with projector.source_radius_m = 0"):
        Scene(projector=Projector(position=(0.0, 0.0, 0.0), source_radius_m=0.0))
    f = tmp_path / "on_camera.toml"
    f.write_text("[projector]\nposition = [0.0, 0.0, 0.0]\nsource_radius_m = 0.0\n")
    with pytest.raises(SceneError) as err:
        load_scene(f)
    assert "\n" not in str(err.value) and "move the source or give it a radius" in str(err.value)
    assert Scene(projector=Projector(position=(0.0, 0.0, 0.0))).separation_m() == 0.0  # radius 1 mm
    assert Scene(projector=Projector(position=(0.01, 0.0, 0.0), source_radius_m=0.0)).separation_m() == 0.01


def test_a_resized_camera_keeps_the_dn_level():
    """Half the width at the same field of view: a pixel sees 4× the solid angle, so the exposure is quartered
    and a pixel at the centre collects the same electrons per unit radiance (sim/sensor.py's pinhole)."""
    cam = Camera(resolution=(640, 480), exposure_s=0.004)
    small = cam.resized((320, 240))
    assert small.resolution == (320, 240) and small.exposure_s == pytest.approx(0.001, rel=1e-12)
    big, little = electrons_per_radiance(cam), electrons_per_radiance(small)
    assert np.mean(little[119:121, 159:161]) == pytest.approx(np.mean(big[239:241, 319:321]), rel=1e-4)
