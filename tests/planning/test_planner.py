import json
import math
import subprocess
import sys

import jsonschema
import numpy as np
import pytest
from polarstripe.planning.plan_cli import PLAN_SCHEMA, plan_to_json
from polarstripe.planning.planner import (
    IDEAL_SENSOR,
    Curve,
    Samples,
    SceneModel,
    SensorNoise,
    compare_scans,
    default_separations,
    objective,
    plan,
)
from polarstripe.sim.scene import SceneError, load_scene


@pytest.fixture(scope="module")
def paper_geometry():
    """The paper's Fig. 8 simulation: isotropic point source on the tank's front facade (which extends past
    every separation swept), pinhole camera, observed point O at the image centre."""
    scene = load_scene(None)
    med = scene.medium
    return scene.replace(projector=scene.projector.replace(model="point"),
                         medium=med.replace(extent=med.extent.replace(min=(-1.0, -1.0, 0.0),
                                                                      max=(1.0, 1.0, 0.38))))


def _centre(scene):
    w, h = scene.camera.resolution
    return [[h // 2, w // 2]]


def test_objective_matches_eq8_and_eq9_without_noise():
    s = Samples(np.array([0.2]), np.array([0.1]), np.array([0.5]), np.array([0.8]))
    flood = objective(s, IDEAL_SENSOR, modality="flood", polarized=True)
    assert flood.value[0] == pytest.approx(0.3 / (0.3 + 0.5 * 0.2))
    stripes = objective(s, IDEAL_SENSOR, modality="stripes", polarized=False)
    assert stripes.value[0] == pytest.approx((0.2 + 0.5) / (0.2 + 0.1 + 0.5))


def test_weight_follows_the_recovered_signal_noise():
    # 100 e- of signal on 300 e- of backscatter, read noise 3 e-: sigma = sqrt(409), W = Phi(S/sigma - 3)
    from scipy.stats import norm

    s = Samples(np.array([100.0]), np.array([0.0]), np.array([300.0]), np.array([0.8]))
    obj = objective(s, SensorNoise(1.0, read_noise_e=3.0), modality="flood", polarized=False)
    assert obj.weight[0] == pytest.approx(norm.cdf(100 / math.sqrt(409) - 3), abs=0.01)
    sat = objective(s, SensorNoise(1.0, full_well_e=350.0), modality="flood", polarized=False)
    assert sat.saturated[0] and sat.value[0] == 0.0


def test_noise_free_curve_rises_monotonically(paper_geometry):
    model = SceneModel(paper_geometry, fidelity="preview", pixels=_centre(paper_geometry))
    curve = plan(model, default_separations(15, 0.02, 0.6), modalities=("flood",))["flood"].curve
    assert np.all(np.diff(curve.objective_noise_free) > 0)


@pytest.mark.parametrize("key", ["flood", "flood_polarized"])
def test_sensor_noise_gives_an_interior_maximum_stable_under_refinement(paper_geometry, key):
    model = SceneModel(paper_geometry, fidelity="preview", pixels=_centre(paper_geometry))
    coarse = default_separations(15, 0.02, 0.6)
    fine = default_separations(29, 0.02, 0.6)  # every coarse point kept, step halved
    c = plan(model, coarse, modalities=("flood",), exposure="auto")[key].curve
    f = plan(model, fine, modalities=("flood",), exposure="auto")[key].curve
    assert 0 < c.best_index < len(coarse) - 1
    assert 0 < f.best_index < len(fine) - 1
    assert c.objective[c.best_index] > c.objective[0] and c.objective[c.best_index] > c.objective[-1]
    assert np.all(c.objective <= c.objective_noise_free + 1e-12)
    assert abs(f.best_separation_m - c.best_separation_m) <= (coarse[1] - coarse[0]) + 1e-12


def _bump(seps, centre, width=0.05):
    return np.exp(-0.5 * ((seps - centre) / width) ** 2)


def _curves(seps, centres):
    out = []
    for c in centres:
        q = _bump(seps, c)
        out.append(Curve(seps, q, q, q, np.ones_like(q), np.zeros(q.size, bool)))
    return out


def test_scan_comparison_known_answers():
    seps = default_separations(60, 0.01, 0.6)
    lateral = np.array([-0.1, 0.0, 0.1])
    # each location's optimum sits a fixed 0.2 m beyond its lateral position: translating wins
    res = compare_scans(seps, _curves(seps, lateral + 0.2), lateral)
    assert res["winner"] == "translate"
    assert res["scores"]["translate"] == pytest.approx(1.0, abs=1e-3)
    assert res["scores"]["rotate"] < 0.5
    # one common optimum: rotating about one source position is enough
    res = compare_scans(seps, _curves(seps, [0.3, 0.3, 0.3]), lateral)
    assert res["winner"] == "rotate" and res["separations_m"]["rotate"][0] == pytest.approx(0.3, abs=0.01)
    # unrelated optima: only moving and turning serves every stripe
    res = compare_scans(seps, _curves(seps, [0.5, 0.1, 0.45]), lateral)
    assert res["winner"] == "both"


def test_stripe_plan_json_validates():
    scene = load_scene(None)
    w, h = scene.camera.resolution
    model = SceneModel(scene, fidelity="preview", pixels=[[h // 2, w // 4], [h // 2, w // 2]])
    doc = plan_to_json(plan(model, default_separations(6, 0.05, 0.5)))
    jsonschema.validate(doc, PLAN_SCHEMA)
    assert set(doc) == {"flood", "flood_polarized", "stripes", "stripes_polarized"}
    entry = doc["stripes_polarized"]
    assert len(entry["locations"]) == 2 and entry["scan"]["winner"] in ("rotate", "translate", "both")
    assert entry["best_separation"] in entry["separations"]
    broken = json.loads(json.dumps(doc))
    del broken["flood"]["objective_noise_free"]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(broken, PLAN_SCHEMA)


def test_stripe_samples_are_lit_by_their_stripe():
    scene = load_scene(None)
    w, h = scene.camera.resolution
    model = SceneModel(scene, fidelity="preview", pixels=[[h // 2, w // 2]])
    s = model.stripes(0.2)
    flood = model.flood(0.2)
    # O is lit, so D equals the flood value; the thin sheet leaves much less backscatter on O's ray
    assert s.direct[0] == pytest.approx(flood.direct[0], rel=1e-9) and s.direct[0] > 0
    assert 0 < s.backscatter[0] < 0.2 * flood.backscatter[0]


def test_bad_input():
    scene = load_scene(None)
    with pytest.raises(SceneError, match="see no object"):
        SceneModel(scene, pixels=[[0, 0]])
    model = SceneModel(scene, fidelity="preview")
    with pytest.raises(SceneError, match="separations"):
        plan(model, [0.3, 0.2])
    with pytest.raises(SceneError, match="separations"):
        plan(model, [0.1, float("nan")])
    with pytest.raises(SceneError, match="modality"):
        plan(model, [0.1, 0.2], modalities=("laser",))
    with pytest.raises(SceneError, match="d_min"):
        default_separations(10, 0.0, 0.5)


def test_plan_command_json_and_plot(tmp_path):
    png = tmp_path / "plan.png"
    out = subprocess.run([sys.executable, "-m", "polarstripe", "plan", "--modality", "flood", "--json",
                          "--separations", "5", "--fidelity", "preview", "--plot", str(png)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    jsonschema.validate(doc, PLAN_SCHEMA)
    assert set(doc) == {"flood", "flood_polarized"}
    assert png.stat().st_size > 10_000


def test_plan_command_bad_scene_is_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[medium]\nsigma_t = -1\n")
    out = subprocess.run([sys.executable, "-m", "polarstripe", "plan", str(bad)], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 2 and "sigma_t" in out.stderr and "Traceback" not in out.stderr


def test_measured_edge_sees_the_backscatter_eq9_ignores():
    # near-coaxial source: the neighbour O' also looks through the sheet's backscatter, so the rendered step
    # (E_O - E_O')/E_O is well below eq. 9, which assumes O' receives only A
    scene = load_scene(None)
    w, h = scene.camera.resolution
    pix = [[h // 2, w // 2]]
    s_eq9 = SceneModel(scene, fidelity="preview", pixels=pix).stripes(0.03)
    s_meas = SceneModel(scene, fidelity="preview", pixels=pix, edge="measured").stripes(0.03)
    q9 = objective(s_eq9, IDEAL_SENSOR, modality="stripes", polarized=False).quality[0]
    qm = objective(s_meas, IDEAL_SENSOR, modality="stripes", polarized=False).quality[0]
    nb = s_meas.neighbour
    assert nb.direct[0] == 0.0 and nb.backscatter[0] > 0  # O is not directly lit by the adjacent sheet
    e_o = s_meas.direct[0] + s_meas.indirect[0] + s_meas.backscatter[0]
    e_n = nb.direct[0] + nb.indirect[0] + nb.backscatter[0]
    assert qm == pytest.approx((e_o - e_n) / e_o, rel=1e-9)
    assert 0.0 <= qm < q9 <= 1.0
    with pytest.raises(SceneError, match="edge"):
        SceneModel(scene, edge="gradient")
