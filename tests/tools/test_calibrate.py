"""Projector–camera calibration against the simulator's truth (docs/depth.md "Calibration").

The truth is the scene's own pinholes (sim/depth_truth.py ``rig_geometry``: f = w/(2·tan(fov/2)), c = w/2 − ½,
R and T from the poses in the scene), not anything the calibration computes. The renders (8 board poses at
320×240, projector 256×192: 34 frames a pose) are made once per medium for this module: about 5 s in clear
water, 35 s at σ_t = 2, plus ~7 s of decoding each.
"""

from __future__ import annotations

import argparse
import os
import re

import numpy as np
import pytest
from polarstripe.imaging.calibration import (
    MURK_CONTRAST,
    Board,
    CalibrationError,
    PoseError,
    calibrate,
    decode_pose,
    failed_poses,
    load,
    save,
)
from polarstripe.imaging.triangulation import RigGeometry
from polarstripe.nodes.compositor_depth import GeometryError, load_geometry, read_calibration
from polarstripe.sim.depth_truth import rig_geometry
from polarstripe.tools import calibrate_cli
from polarstripe.tools.cli import main as cli

POSES = 8
BOARD = Board(8, 6, 0.015)


def _args(*extra: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    calibrate_cli.configure(parser)
    return parser.parse_args(["-o", "unused.yaml", "--sim", "--resolution", "320x240",
                              "--projector", "256x192", *extra])


@pytest.fixture(scope="module", params=[0.0, 2.0], ids=["clear", "sigma_t=2"])
def rig(request, tmp_path_factory):
    """(scene, frames of every pose, decoded poses) of the simulated rig in one medium."""
    args = _args("--sigma-t", str(request.param))
    scene = calibrate_cli.rig_scene(args)
    tex = str(tmp_path_factory.mktemp("board") / "board.png")
    size = calibrate_cli.board_texture(BOARD, tex)
    poses = calibrate_cli.random_poses(POSES, 0, scene, BOARD.cols, BOARD.rows, BOARD.square_m)
    rng = np.random.default_rng(0)
    angle = calibrate_cli.crossed_angle(scene, "preview", rng)        # E_b; None in clear water
    assert (angle is None) == (request.param == 0.0)
    frames = []
    for p in poses:                                                    # each pose exposed for itself
        lit = calibrate_cli.exposed(scene, p, tex, size, "preview", polarizer_deg=angle)
        frames.append(calibrate_cli.render_pose(lit, p, tex, size, rng, "preview", polarizer_deg=angle))
    proj = tuple(scene.projector.resolution)
    decoded = [decode_pose(*f, BOARD, proj, pose=k) for k, f in enumerate(frames)]
    return scene, frames, decoded


def test_calibration_matches_the_simulators_truth(rig):
    scene, _, decoded = rig
    truth = rig_geometry(scene)
    cal = calibrate(decoded, BOARD, tuple(scene.camera.resolution), tuple(scene.projector.resolution))
    for name, K, Kt in (("camera", cal.K_cam, truth["K_cam"]), ("projector", cal.K_proj, truth["K_proj"])):
        for i in (0, 1):
            assert abs(K[i, i] / Kt[i, i] - 1) < 0.005, f"{name} focal length {K[i, i]} vs {Kt[i, i]}"
            assert abs(K[i, 2] - Kt[i, 2]) < 2.0, f"{name} principal point {K[i, 2]} vs {Kt[i, 2]}"
    assert abs(np.linalg.norm(cal.T) - np.linalg.norm(truth["T"])) < 1e-3          # baseline within 1 mm
    assert np.linalg.norm(cal.T - truth["T"]) < 2e-3                               # and its direction
    dR = cal.R @ np.asarray(truth["R"]).T
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.1
    assert cal.rms_cam < 0.3 and cal.rms_proj < 0.3 and cal.rms_stereo < 0.3


def test_the_file_is_what_the_compositor_reads(rig, tmp_path):
    scene, _, decoded = rig
    cal = calibrate(decoded, BOARD, tuple(scene.camera.resolution), tuple(scene.projector.resolution))
    path = str(tmp_path / "rig.yaml")
    save(path, {**cal.geometry(), "dist_proj": cal.dist_proj}, {"rms_cam": cal.rms_cam})
    g = load_geometry(path)
    assert isinstance(g, RigGeometry) and g.cam_size == (320, 240) and g.proj_size == (256, 192)
    np.testing.assert_allclose(g.K_proj, cal.K_proj)
    np.testing.assert_allclose(g.T, cal.T)
    # a camera binned 2×2 is the same rig; another projector or camera aspect is not
    assert load(path, cam_size=(160, 120), proj_size=(256, 192))["K_cam"].shape == (3, 3)
    with pytest.raises(GeometryError, match="256x192 projector, the rig's is 1024x768"):
        read_calibration(path, proj_size=(1024, 768))
    with pytest.raises(CalibrationError, match="320x240 camera, the rig's is 640x400"):
        load(path, cam_size=(640, 400))


def test_too_few_poses_is_one_error(rig):
    scene, _, decoded = rig
    with pytest.raises(CalibrationError, match="2 usable poses: a calibration needs at least 3"):
        calibrate(decoded[:2], BOARD, tuple(scene.camera.resolution), tuple(scene.projector.resolution))


def test_a_board_not_seen_is_one_error(rig):
    scene, frames, _ = rig
    white, black, gray = frames[0]
    blank = np.full_like(white, int(np.percentile(white, 99)))     # lit, but no board in view
    with pytest.raises(CalibrationError, match="pose 3: the 8x6 checkerboard is not seen"):
        decode_pose(blank, black, gray, BOARD, tuple(scene.projector.resolution), pose=3)
    with pytest.raises(CalibrationError, match="the 9x6 checkerboard is not seen"):
        decode_pose(white, black, gray, Board(9, 6, 0.015), tuple(scene.projector.resolution))


def test_patterns_the_camera_cannot_decode_are_one_error(rig):
    scene, frames, _ = rig
    white, black, gray = frames[0]
    proj = tuple(scene.projector.resolution)
    with pytest.raises(CalibrationError, match="corners decode in the projector"):
        decode_pose(white, black, [white] * len(gray), BOARD, proj)      # every pattern = its inverse
    with pytest.raises(CalibrationError, match="code frames, a 256x192 projector needs 32"):
        decode_pose(white, black, gray[:-2], BOARD, proj)


def test_a_code_the_murk_drowned_names_the_pose_and_its_contrast(rig):
    """Each pattern pair keeps 1/200 of its difference, the rest becomes light alike under both (as when
    the medium scatters nearly all of the projector's light), under the sensor's noise (10 DN): the pose
    fails with the code's contrast, and the failed poses are one line."""
    scene, frames, _ = rig
    white, black, gray = frames[0]
    dark = float(np.median(black))
    rng = np.random.default_rng(1)
    g = [np.asarray(f, float) - dark for f in gray]
    murky = [dark + 0.5 * (a + b) + s * 0.0025 * (a - b) + rng.normal(0.0, 10.0, a.shape)
             for a, b in zip(g[::2], g[1::2], strict=True) for s in (1, -1)]
    with pytest.raises(PoseError, match=r"pose 5: only \d+ of 48 corners decode .*contrast on the board is "
                                        r"\d\.\d % of the light .*the murk\)$") as err:
        decode_pose(white, black, murky, BOARD, tuple(scene.projector.resolution), pose=5)
    assert 0.0 < err.value.contrast < MURK_CONTRAST
    other = PoseError(2, "the 8x6 checkerboard is not seen in the white frame")
    line = failed_poses([err.value, PoseError(6, "x", 0.001), other])
    assert line.startswith("poses 5, 6: the code's contrast is 0.1-") and ": the murk)" in line
    assert line.endswith("; pose 2: the 8x6 checkerboard is not seen in the white frame")
    assert "\n" not in line


def test_cli_writes_the_file_and_the_coverage_view(tmp_path, capsys):
    out = tmp_path / "rig.yaml"
    assert cli(["calibrate", "-o", str(out), "--sim", "--poses", "4", "--sigma-t", "0", "--resolution",
                "320x240", "--projector", "64x48", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "baseline" in printed and "rotation error" in printed
    g = load(str(out), proj_size=(64, 48))
    assert abs(np.linalg.norm(g["T"]) - 0.2) < 0.01                              # the default tank's 20 cm
    assert (tmp_path / "rig_coverage.png").stat().st_size > 0
    # --check: the file beside the scene's rig; the default tank's 1024x768 projector is another rig size
    assert cli(["calibrate", "--check", str(out), "--resolution", "160x120", "--projector", "64x48"]) == 0
    assert "baseline" in capsys.readouterr().out
    assert cli(["calibrate", "--check", str(out)]) == 2
    assert "is for a 64x48 projector, the rig's is 1024x768: calibrate this rig" in capsys.readouterr().err


def test_a_failed_run_leaves_the_previous_file_untouched(tmp_path, capsys):
    out = tmp_path / "rig.yaml"
    out.write_text("%YAML:1.0\nprevious: 1\n")
    before = out.read_bytes()
    assert cli(["calibrate", "-o", str(out), "--sim", "--poses", "2"]) == 2
    assert "needs at least 3 poses" in capsys.readouterr().err
    # the board is 12x9 here: no pose shows it whole in a 160x120 camera (one line, before any render)
    assert cli(["calibrate", "-o", str(out), "--sim", "--poses", "3", "--sigma-t", "0", "--resolution",
                "160x120", "--projector", "64x48", "--board", "12x9", "--square", "0.03",
                "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the 12x9 board of 0.03 m squares is not seen whole by camera and projector " \
                              "at pose 0 in 400 draws" in err[0]
    assert out.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["rig.yaml"]                          # no temporary left behind


def test_a_port_on_one_device_only_is_one_error_before_any_render(tmp_path, capsys):
    scene = tmp_path / "one_port.toml"
    scene.write_text('[camera]\nport = { distance_m = 0.02, thickness_m = 0.01 }\n')
    out = tmp_path / "rig.yaml"
    assert cli(["calibrate", "-o", str(out), "--sim", str(scene), "--poses", "3", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs both camera and projector behind a port; this scene has one only on " \
                              "the camera (--pinhole: the pinhole fit)" in err[0]
    assert not out.exists()


@pytest.mark.long
@pytest.mark.timeout(1200)  # ~40 s of CPU (16 poses of 42 frames through the ports, the fit ~10 s)
def test_calibration_through_the_glass_tank_fits_the_ports(tmp_path, capsys):
    """The paper's glass wall (docs/depth.md "Calibration through a port"): all 16 poses seen, and the file
    holds the refractive rig, its ports near the scene's (d within 1 mm, the normal within 0.5°) and the
    rest within the clear-water tolerances, where the pinhole fit through the same ports is 21° off in
    rotation."""
    scene = tmp_path / "tank.toml"
    scene.write_text('preset = "glass_tank"\n')
    out = tmp_path / "rig.yaml"
    assert cli(["calibrate", "-o", str(out), "--sim", str(scene), "--poses", "16", "--square", "0.012",
                "--sigma-t", "0", "--resolution", "320x240", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "refractive model" in printed
    g = load(str(out))
    parser = argparse.ArgumentParser()
    calibrate_cli.configure(parser)
    truth = rig_geometry(calibrate_cli.rig_scene(parser.parse_args([str(scene), "--resolution", "320x240"])))
    assert "16 poses" in printed
    for key in ("port_cam", "port_proj"):
        assert abs(g[key][3] - truth[key][3]) < 1e-3
        tilt = np.degrees(np.arccos(np.clip(g[key][:3] @ truth[key][:3], -1, 1)))
        assert tilt < 0.5
    for K, Kt in ((g["K_cam"], truth["K_cam"]), (g["K_proj"], truth["K_proj"])):
        assert abs(K[0, 0] / Kt[0, 0] - 1) < 0.005 and abs(K[1, 1] / Kt[1, 1] - 1) < 0.005
        assert abs(K[0, 2] - Kt[0, 2]) < 2.0 and abs(K[1, 2] - Kt[1, 2]) < 2.0
    assert abs(np.linalg.norm(g["T"]) - 0.2) < 1e-3
    dR = g["R"] @ np.asarray(truth["R"]).T
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.1
    rms = re.search(r"RMS camera ([\d.]+) px, projector ([\d.]+) px, stereo ([\d.]+) px", printed).groups()
    assert max(float(v) for v in rms) < 0.3
    assert load_geometry(str(out)).has_ports                                      # what the compositor reads
