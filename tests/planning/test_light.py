"""Linear or circular light: the rig's plates (sim/scene.py ``with_light``), the planner's recommendation
(planning/light.py) and ``polarstripe plan --light``."""

from __future__ import annotations

import json

import jsonschema
import numpy as np
import pytest
from polarstripe.planning.light import TIE, compare_lights
from polarstripe.planning.plan_cli import PLAN_SCHEMA
from polarstripe.planning.planner import default_separations
from polarstripe.sim.patterns import parse_pattern
from polarstripe.sim.scene import SceneError, load_scene, with_light
from polarstripe.sim.transport import make_source
from polarstripe.tools.cli import main


def test_with_light_mounts_and_removes_the_plates():
    scene = load_scene(None)
    circ = with_light(scene, "circular")
    assert circ.projector.polarization.quarter_wave_deg == scene.projector.polarization.angle_deg - 45.0
    assert circ.camera.polarizer.quarter_wave_deg == 45.0
    lin, v = make_source(circ, parse_pattern("flood")).linear_circular
    assert v == pytest.approx(1.0) and abs(lin) < 1e-12          # V_L = +1 (docs/physics.md §5.1)
    back = with_light(circ, "linear")
    assert back == scene
    with pytest.raises(SceneError, match="light must be one of linear, circular, got 'elliptic'"):
        with_light(scene, "elliptic")


@pytest.fixture(scope="module")
def small():
    scene = load_scene(None)
    return scene.replace(camera=scene.camera.resized((40, 30)))


def test_compare_lights_recommends_by_the_expected_error(small):
    """Each light's best objective is 1 − its expected error; the recommendation is circular only when it
    predicts an error lower by more than TIE. Circular light's backscatter DOP is the lower at the pick
    (depolarized Rayleigh: m44/m11 = 1 − 2δ < m22/m11 = 1 − δ in every scattering)."""
    res = compare_lights(small, default_separations(2, 0.1, 0.3), modalities=("flood",), n_stripes=6)
    assert set(res["recommended"]) == {"flood_polarized"} and res["tie"] == TIE
    lin, circ = (res["lights"][k]["flood_polarized"] for k in ("linear", "circular"))
    for e in (lin, circ):
        assert e["expected_error"] == pytest.approx(1.0 - e["objective"])
        assert e["separation_m"] in (0.1, 0.3)
    want = "circular" if circ["objective"] > lin["objective"] + TIE else "linear"
    assert res["recommended"]["flood_polarized"] == want
    assert 0.0 < circ["p"] < lin["p"] < 1.0


def test_plan_command_light_both(capsys):
    assert main(["plan", "--modality", "flood", "--separations", "2", "--stripes", "6", "--light", "both",
                 "--width", "48", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    jsonschema.validate(doc, PLAN_SCHEMA)
    assert doc["light"]["recommended"]["flood_polarized"] in ("linear", "circular")
    assert np.isfinite(doc["light"]["lights"]["circular"]["flood_polarized"]["expected_error"])
    with pytest.raises(SystemExit):
        main(["plan", "--light", "elliptic"])
    assert "invalid choice: 'elliptic'" in capsys.readouterr().err


def test_bench_light_table(capsys):
    """``polarstripe bench light`` end to end on one tiny water: both lights scored through the compositor's
    pipeline, circular light's backscatter DOP on the analyzer's circle below linear light's (§5.1), the
    lower error named per method."""
    assert main(["bench", "light", "--sigma-t", "5", "--g", "0.8", "--resolution", "32x24", "--stripes", "6",
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    (row,) = doc["rows"]
    lin, circ = row["lights"]["linear"], row["lights"]["circular"]
    assert 0.0 < circ["p_seen"] < lin["p_seen"] < 1.0
    for key in ("flood_polarized", "stripes_polarized"):
        errors = {lt: row["lights"][lt][key]["error"] for lt in ("linear", "circular")}
        assert row["e2e_better"][key] == min(errors, key=errors.get)
