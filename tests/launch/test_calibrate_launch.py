"""``launch/calibrate.toml`` end to end: the calibrator shows the Gray code through the emitter, grabs the
frames through the grabber from the simulator (its checkerboard target at 4 poses), writes the calibration
file and the coverage view, and the file's rig matches the scene's own pinholes (sim/depth_truth.py) at a
loose tolerance (the issue's tight ones are held by tests/tools/test_calibrate.py on the pure path)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from polarstripe.imaging.calibration import load
from polarstripe.sim.depth_truth import rig_geometry
from polarstripe.sim.scene import load_scene

ROOT = Path(__file__).resolve().parents[2]


def test_calibration_over_the_nodes_matches_the_scenes_rig(tmp_path):
    scene = tmp_path / "scene.toml"
    scene.write_text("[medium]\nsigma_t = 0.0\n[projector]\nresolution = [256, 192]\n")
    out = tmp_path / "rig.yaml"
    out.write_text("previous\n")
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")}
    proc = subprocess.run([sys.executable, "-m", "polarstripe", "launch", str(ROOT / "launch/calibrate.toml"),
                           "--once", f"out={out}", f"scene={scene}", "projector=256x192", "poses=4",
                           "resolution=320x240"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    (run_dir,) = (tmp_path / "runs").iterdir()
    logs = {p.stem: p.read_text() for p in (run_dir / "logs").iterdir()}
    exits = json.loads((run_dir / "exits.json").read_text())["nodes"]
    assert exits["calibrator"]["exit_code"] == 0, (proc.stderr, logs["calibrator"])
    assert all("Traceback" not in text for text in logs.values())
    assert logs["calibrator"].count("pixels decoded around the corners") == 4
    assert (tmp_path / "rig_coverage.png").stat().st_size > 0
    truth = rig_geometry(load_scene(str(scene)).replace(
        camera=load_scene(str(scene)).camera.replace(resolution=(320, 240))))
    g = load(str(out), cam_size=(320, 240), proj_size=(256, 192))
    for K, T in ((g["K_cam"], truth["K_cam"]), (g["K_proj"], truth["K_proj"])):
        assert abs(K[0, 0] / T[0, 0] - 1) < 0.01 and abs(K[1, 1] / T[1, 1] - 1) < 0.01, (K, T)
        assert np.hypot(K[0, 2] - T[0, 2], K[1, 2] - T[1, 2]) < 2, (K, T)
    assert abs(np.linalg.norm(g["T"]) - np.linalg.norm(truth["T"])) < 0.002
    dR = g["R"] @ truth["R"].T
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.3


@pytest.mark.long
@pytest.mark.timeout(900)  # 16 poses of 42 frames through the ports: ~1 minute of CPU, more when loaded
def test_calibration_over_the_nodes_through_the_glass_wall_fits_the_ports(tmp_path):
    """``port=glass_tank`` (docs/depth.md "Calibration through a port"): the file holds the refractive rig,
    its ports near the scene's and its pose within the loose tolerances above."""
    scene = tmp_path / "tank.toml"
    scene.write_text('preset = "glass_tank"\n[medium]\nsigma_t = 0.0\n')
    out = tmp_path / "rig.yaml"
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")}
    proc = subprocess.run([sys.executable, "-m", "polarstripe", "launch", str(ROOT / "launch/calibrate.toml"),
                           "--once", f"out={out}", f"scene={scene}", "poses=16", "square_m=0.012",
                           "resolution=320x240", "port=glass_tank"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=800)
    (run_dir,) = (tmp_path / "runs").iterdir()
    log = (run_dir / "logs" / "calibrator.log").read_text()
    assert proc.returncode == 0 and "refractive (flat ports)" in log, (proc.stderr, log)
    truth = rig_geometry(load_scene(str(scene)).replace(
        camera=load_scene(str(scene)).camera.replace(resolution=(320, 240))))
    g = load(str(out), cam_size=(320, 240))
    for key, tol_m in (("port_cam", 5e-3), ("port_proj", 1.5e-3)):
        assert abs(g[key][3] - truth[key][3]) < tol_m, (key, g[key], truth[key])
        assert np.degrees(np.arccos(np.clip(g[key][:3] @ truth[key][:3], -1, 1))) < 1.5, (key, g[key])
    assert abs(np.linalg.norm(g["T"]) - np.linalg.norm(truth["T"])) < 0.002
    dR = g["R"] @ truth["R"].T
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.3
