"""A corrupt rig calibration file is one line naming the file and what is wrong with it, never OpenCV's
``SystemError`` traceback: in a scene (``calibration = "rig.yaml"``), in ``polarstripe plan`` and in
``polarstripe calibrate --check`` (sim/filestorage.py)."""

from __future__ import annotations

import pytest
from polarstripe.imaging.calibration import CalibrationError, load
from polarstripe.sim.scene import SceneError, load_scene
from polarstripe.tools.cli import main

MATRIX = "K_cam: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
# file text -> what the one line must say (the parser's complaint with its line, or the key and the fault)
CORRUPT = {
    "": "the file is empty",
    "\x89PNG\r\n\x1a\n\x00\x00binary": "not an OpenCV FileStorage file",
    "just some words\n": "line 1: ",
    "%YAML:1.0\n---\n" + MATRIX + "   data: [ 1., 0.,\n": "line 7: Missing , between the elements",
    "%YAML:1.0\n---\n" + MATRIX + "   data: [ 1., 0. ]\n": "K_cam: a matrix whose data do not fit its rows",
    "%YAML:1.0\n---\nK_cam: not a matrix\n": "key K_cam holds no numbers",
    "%YAML:1.0\n---\nK_cam: [1, 2, 3]\n": "key K_proj is missing",
}


@pytest.fixture(params=list(CORRUPT), ids=[f"case{i}" for i in range(len(CORRUPT))])
def bad_file(request, tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_bytes(request.param.encode("latin-1"))
    (tmp_path / "scene.toml").write_text('calibration = "rig.yaml"\n')
    return path, CORRUPT[request.param]


def test_the_scene_key_refuses_it_in_one_line(bad_file):
    path, said = bad_file
    with pytest.raises(SceneError, match="rig.yaml") as err:
        load_scene(path.parent / "scene.toml")
    assert said in str(err.value) and "\n" not in str(err.value)


def test_the_calibration_reader_refuses_it_in_one_line(bad_file):
    path, said = bad_file
    with pytest.raises(CalibrationError, match="rig.yaml") as err:
        load(str(path))
    assert said in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("command", ["plan", "calibrate --check"])
def test_the_commands_end_in_one_line(bad_file, command, capsys):
    path, said = bad_file
    argv = ["plan", str(path.parent / "scene.toml")] if command == "plan" else \
        ["calibrate", "--check", str(path)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"polarstripe {command.split()[0]}: error: ")
    assert said in err and "rig.yaml" in err and "Traceback" not in err and "SystemError" not in err
