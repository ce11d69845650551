"""Several light sheets per frame through the node set: the demo launch with ``sheets=3`` ends by itself with
metrics (long: a minute and more at load), and a small rig of its own (simulator, grabber, emitter,
compositor, sequencer; no stage: unpolarized stripes) scans 8 stripes in 4 two-sheet frames and triangulates
them."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def launch(tmp_path, file, *overrides, timeout=120):
    env = {**os.environ, "POLARSTRIPE_RUNS": str(tmp_path / "runs")}
    proc = subprocess.run([sys.executable, "-m", "polarstripe", "launch", str(file), "--once", *overrides],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=timeout)
    (run_dir,) = (tmp_path / "runs").iterdir()
    logs = {p.stem: p.read_text() for p in (run_dir / "logs").iterdir()}
    return proc, logs


def test_a_two_sheet_stripe_scan_runs_through_the_nodes_in_half_the_frames(tmp_path):
    out = tmp_path / "out"
    f = tmp_path / "sheets.toml"
    f.write_text(f"""
[launch]
name = "sheets"
namespace = "/rig"
[launch.env]
OMP_NUM_THREADS = "1"
[[node]]
name = "simulator"
module = "polarstripe.nodes.simulator"
params = {{ resolution = "64x48" }}
[[node]]
name = "grabber"
module = "polarstripe.nodes.grabber"
[[node]]
name = "compositor"
module = "polarstripe.nodes.compositor"
params = {{ out = "{out}" }}
[[node]]
name = "emitter"
module = "polarstripe.nodes.emitter"
params = {{ stripes = 8 }}
[[node]]
name = "sequencer"
module = "polarstripe.nodes.sequencer"
params = {{ methods = ["stripes"], stripes = 8, sheets = 2, plan = false }}
required = true
""")
    proc, logs = launch(tmp_path, f)
    assert proc.returncode == 0, proc.stderr + logs.get("sequencer", "")
    m = json.loads((out / "metrics.json").read_text())["stripes"]
    assert (m["frames"], m["sheets"], m["stripes"]) == (4, 2, 8)
    depth = m["depth"]
    assert depth["sheets"] == 2 and depth["depth_range_from"] == "simulator/truth"
    assert depth["valid_fraction"] > 0.2 and depth["depth_rms_mm"] < 15.0
    assert (out / "depth_stripes.npy").is_file()


@pytest.mark.long
def test_the_demo_with_three_sheets_ends_by_itself_with_metrics(tmp_path):
    """``polarstripe launch launch/sim.toml --once sheets=3``, small: the stripe methods take ⌈9/3⌉ frames
    per pass and give a depth; every method its composite."""
    out = tmp_path / "out"
    proc, logs = launch(tmp_path, ROOT / "launch" / "sim.toml", f"out={out}", "resolution=96x72", "stripes=9",
                        "sheets=3", timeout=300)
    assert proc.returncode == 0, proc.stderr + logs.get("sequencer", "")
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"flood", "polarized_flood", "stripes", "polarized_stripes", "hf_separation"}
    assert metrics["stripes"]["frames"] == 3 and metrics["polarized_stripes"]["frames"] == 6
    for method in ("stripes", "polarized_stripes"):
        assert metrics[method]["sheets"] == 3 and metrics[method]["depth"]["valid_fraction"] > 0.1
    assert "depth valid" in logs["sequencer"]               # the results table the launch ends with


@pytest.mark.long
def test_the_polarization_camera_with_three_sheets_scans_polarized_stripes_in_n_over_k_frames(tmp_path):
    """``launch/sim_polarization.toml sheets=3``: one pass, ⌈9/3⌉ frames of polarized stripes, with depth."""
    out = tmp_path / "out"
    proc, logs = launch(tmp_path, ROOT / "launch" / "sim_polarization.toml", f"out={out}", "resolution=96x72",
                        "stripes=9", "sheets=3", timeout=300)
    assert proc.returncode == 0, proc.stderr + logs.get("sequencer", "")
    m = json.loads((out / "metrics.json").read_text())["polarized_stripes"]
    assert (m["frames"], m["sheets"]) == (3, 3) and m["depth"]["valid_fraction"] > 0.1
