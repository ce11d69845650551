"""The scene key ``calibration`` (sim/scene_calibration.py): a rig calibration file sets the camera's and
projector's pinholes; a file written from a known rig gives that rig back; bad files are one clear error."""

from __future__ import annotations

import numpy as np
import pytest
from polarstripe.imaging.calibration import save
from polarstripe.sim.depth_truth import rig_geometry
from polarstripe.sim.scene import Scene, SceneError, glass_tank, load_scene, with_separation


def known_rig() -> Scene:
    """The default tank with the projector moved and turned, the camera at 640x480, fov 50°."""
    s = Scene()
    s = s.replace(camera=s.camera.replace(fov_deg=50.0),
                  projector=s.projector.replace(resolution=(800, 600), fov_deg=40.0, up=(0.1, 1.0, 0.0)))
    return with_separation(s, 0.15)


def write(tmp_path, geom, text="", **changes):
    g = {**geom, "dist_proj": np.zeros(5), **changes}
    save(str(tmp_path / "rig.yaml"), g)
    (tmp_path / "scene.toml").write_text('calibration = "rig.yaml"\n' + text)
    return tmp_path / "scene.toml"


def test_a_calibration_file_gives_the_rig_it_was_written_from(tmp_path):
    rig = known_rig()
    scene = load_scene(write(tmp_path, rig_geometry(rig)))
    assert scene.camera.resolution == (640, 480) and scene.projector.resolution == (800, 600)
    assert scene.camera.fov_deg == pytest.approx(50.0, abs=1e-9)
    assert scene.projector.fov_deg == pytest.approx(40.0, abs=1e-9)
    assert np.allclose(scene.projector.position, rig.projector.position, atol=1e-9)
    f_true = np.subtract(rig.projector.look_at, rig.projector.position)
    f_got = np.subtract(scene.projector.look_at, scene.projector.position)
    assert np.allclose(f_got / np.linalg.norm(f_got), f_true / np.linalg.norm(f_true), atol=1e-9)
    def image_up(p):  # u = r × f, r = normalize(f × up) (docs/scene-format.md "Geometry")
        f = np.subtract(p.look_at, p.position)
        f /= np.linalg.norm(f)
        r = np.cross(f, p.up)
        return np.cross(r / np.linalg.norm(r), f)

    assert np.allclose(image_up(scene.projector), image_up(rig.projector), atol=1e-9)
    g = rig_geometry(scene)
    for key in ("K_cam", "K_proj", "R", "T"):
        assert np.allclose(g[key], rig_geometry(rig)[key], atol=1e-9), key


def test_a_binned_camera_is_the_same_rig(tmp_path):
    scene = load_scene(write(tmp_path, rig_geometry(known_rig()), "[camera]\nresolution = [320, 240]\n"))
    assert scene.camera.resolution == (320, 240) and scene.camera.fov_deg == pytest.approx(50.0)


@pytest.mark.parametrize("text, changes, match", [
    ("[camera]\nresolution = [300, 200]\n", {}, "640x480 camera; the rig's is 300x200"),
    ("[projector]\nresolution = [1024, 768]\n", {}, "800x600 projector; the rig's is 1024x768"),
    ("[projector]\nfov_deg = 30\n", {}, "projector.fov_deg is set by the calibration file"),
    ("", {"K_cam": np.array([[550.0, 0, 400], [0, 550, 239.5], [0, 0, 1]])}, "principal point"),
    ("", {"K_proj": np.array([[500.0, 0, 399.5], [0, 530, 299.5], [0, 0, 1]])}, "square"),
])
def test_another_rig_is_one_clear_error(tmp_path, text, changes, match):
    with pytest.raises(SceneError, match=match):
        load_scene(write(tmp_path, rig_geometry(known_rig()), text, **changes))


def test_a_missing_file_is_one_clear_error(tmp_path):
    (tmp_path / "scene.toml").write_text('calibration = "nowhere.yaml"\n')
    with pytest.raises(SceneError, match="nowhere.yaml.*no such file"):
        load_scene(tmp_path / "scene.toml")


def test_a_file_written_through_ports_gives_the_ports_back(tmp_path):
    """The glass wall's rig (the projector's port 27° off its axis) through a file: each device's port in its
    own frame, the intrinsics and the pose as written; the scene's ``coated`` kept; a scene that sets a port
    the file has is one error."""
    rig = rig_geometry(glass_tank(Scene()))
    scene = load_scene(write(tmp_path, rig, 'preset = "glass_tank"\n'))
    g = rig_geometry(scene)
    for key in ("K_cam", "K_proj", "R", "T", "port_cam", "port_proj"):
        assert np.allclose(g[key], rig[key], atol=1e-9), key
    assert scene.camera.port.coated and scene.projector.port.coated
    plain = load_scene(write(tmp_path, rig))
    assert np.allclose(rig_geometry(plain)["port_proj"], rig["port_proj"], atol=1e-9)
    assert not plain.projector.port.coated                           # no scene port: the Port default
    with pytest.raises(SceneError, match="camera.port is set by the calibration file"):
        load_scene(write(tmp_path, rig, "[camera]\nport = \"glass_tank\"\n"))
