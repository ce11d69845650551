"""Scene files: defaults, round trip, and one clear error naming the key for each bad input."""

import numpy as np
import pytest
from polarstripe.sim.scene import SceneError, load_scene, scene_from_dict, scene_to_dict, with_separation


def test_default_is_the_papers_tank():
    s = load_scene(None)
    lo, hi = np.array(s.medium.extent.min), np.array(s.medium.extent.max)
    np.testing.assert_allclose(hi - lo, [0.6, 0.6, 0.38])
    assert s.medium.phase.model == "tthg" and s.medium.phase.g == 0.8
    assert s.camera.position[2] == lo[2] and s.projector.position[2] == lo[2]      # both on the front face
    chart = s.objects[0]
    assert chart.texture == "chart" and chart.albedo == 0.6 and chart.point[2] == hi[2]


def test_toml_round_trip(tmp_path):
    text = """
[medium]
sigma_t = 3.5
albedo = 0.9
phase = {model = "hg", g = 0.7}
dop = {model = "constant", p = 0.6}
extent = {min = [-1, -1, 0], max = [1, 1, 2]}
[camera]
resolution = [32, 24]
polarizer = {angle_deg = 10, extinction_ratio = 500}
[projector]
model = "point"
position = [0.1, 0, 0]
[[object]]
type = "sphere"
center = [0, 0, 1]
radius = 0.2
albedo = 0.3
"""
    p = tmp_path / "s.toml"
    p.write_text(text)
    s = load_scene(p)
    assert s.medium.sigma_t == 3.5 and s.medium.phase.model == "hg" and s.medium.phase.g == 0.7
    assert s.camera.resolution == (32, 24) and s.camera.polarizer.angle_deg == 10
    assert s.projector.model == "point" and s.objects[0].radius == 0.2
    again = scene_from_dict(scene_to_dict(s))
    assert again == s


@pytest.mark.parametrize("text, key", [
    ("[medium]\nsigma_q = 1", "medium.sigma_q"),
    ("[medium]\nsigma_t = -1", "medium.sigma_t"),
    ("[medium]\nalbedo = 1.5", "medium.albedo"),
    ("[medium]\nsigma_t = nan", "medium.sigma_t"),
    ("[camera]\nlook_at = [0, 0, 0]", "camera.look_at"),
    ("[projector]\nposition = [0, 0, 0.38]\nlook_at = [0, 0, 0.38]", "projector.look_at"),
    ("[[object]]\ntype = \"plane\"\nalbedo = -0.1", "object[0].albedo"),
    ("[[object]]\ntype = \"plane\"\ncolour = 3", "object[0].colour"),
    ("[medium]\nphase = {model = \"tthg\", mean_cosine = 1.2}", "medium.phase.mean_cosine"),
    ("[camera]\nresolution = [0, 10]", "camera.resolution"),
    ("[wat]\nx = 1", "scene.wat"),
])
def test_bad_scene_gives_one_error_naming_the_key(tmp_path, text, key):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(SceneError, match=key.replace("[", r"\[").replace("]", r"\]")):
        load_scene(p)


def test_not_toml_is_a_scene_error(tmp_path):
    p = tmp_path / "x.toml"
    p.write_text("this is = = not toml")
    with pytest.raises(SceneError, match="not a valid TOML"):
        load_scene(p)


def test_replace_validates_and_separation_moves_along_front_face():
    s = load_scene(None)
    with pytest.raises(SceneError, match="medium.albedo"):
        s.medium.replace(albedo=2.0)
    for d in (0.05, 0.4, 0.6):
        moved = with_separation(s, d)
        assert moved.separation_m() == pytest.approx(d, abs=1e-12)
        assert moved.projector.position[2] == pytest.approx(s.camera.position[2], abs=1e-15)
        assert moved.projector.look_at == s.projector.look_at
    same_dir = with_separation(s, 0.3, aim=False)
    np.testing.assert_allclose(np.subtract(same_dir.projector.look_at, same_dir.projector.position),
                               np.subtract(s.projector.look_at, s.projector.position))


def test_a_file_has_the_objects_it_lists(tmp_path):
    """No [[object]] (or ``object = []``): no objects; the tank's chart comes only with the tank itself."""
    for name, text in (("none.toml", "[medium]\nsigma_t = 2.0\n"), ("empty.toml", "object = []\n"),
                       ("blank.toml", "")):
        p = tmp_path / name
        p.write_text(text)
        assert load_scene(p).objects == ()
    assert scene_from_dict({}).objects == () and load_scene(None).objects[0].texture == "chart"
