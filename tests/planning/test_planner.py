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
    recommend_reading,
)
from polarstripe.planning.scene_model import fig8_scene, part_frame
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import SceneError, load_scene, with_separation


@pytest.fixture(scope="module")
def paper_geometry():
    """The paper's Fig. 8 simulation: isotropic point source on the tank's front facade (which extends past
    every separation swept), pinhole camera, a Lambertian plane of albedo 0.6, sigma_t = 6 /m."""
    return fig8_scene(sigma_t=6.0)


@pytest.fixture(scope="module")
def fig8_flood(paper_geometry):
    w, h = paper_geometry.camera.resolution
    # Fig. 9a is the paper's single-scattering model (with all orders the noise-free E_b curve peaks inside
    # the range: forward scatter brings the far source's object light back; docs/planning.md §7)
    model = SceneModel(paper_geometry, fidelity="preview", pixels=[[h // 2, w // 2]], orders="single")
    coarse, fine = default_separations(15, 0.02, 0.6), default_separations(29, 0.02, 0.6)
    return (coarse, plan(model, coarse, modalities=("flood",), exposure="auto"),
            plan(model, fine, modalities=("flood",), exposure="auto"))


def test_objective_matches_eq8_and_eq9_without_noise():
    s = Samples(np.array([0.2]), np.array([0.1]), np.array([0.5]), np.array([0.8]))
    flood = objective(s, IDEAL_SENSOR, modality="flood", reading="E_b")
    assert flood.value[0] == pytest.approx(0.3 / (0.3 + 0.5 * 0.2))
    stripes = objective(s, IDEAL_SENSOR, modality="stripes", reading="E", edge="eq9")
    assert stripes.value[0] == pytest.approx((0.2 + 0.5) / (0.2 + 0.1 + 0.5))


def test_weight_follows_the_recovered_signal_noise():
    # 100 e- of signal on 300 e- of backscatter, read noise 3 e-: sigma = sqrt(409), W = Phi(S/sigma - 3)
    from scipy.stats import norm

    s = Samples(np.array([100.0]), np.array([0.0]), np.array([300.0]), np.array([0.8]))
    obj = objective(s, SensorNoise(1.0, read_noise_e=3.0), modality="flood", reading="E")
    assert obj.weight[0] == pytest.approx(norm.cdf(100 / math.sqrt(409) - 3), abs=0.01)
    sat = objective(s, SensorNoise(1.0, full_well_e=350.0), modality="flood", reading="E")
    assert sat.saturated[0] and sat.value[0] == 0.0


@pytest.mark.parametrize("key", ["flood", "flood_polarized"])
def test_fig8_flood_noise_free_curves_rise_monotonically(fig8_flood, key):
    _, plans, _ = fig8_flood
    for reading, curve in (plans[key].readings or {"E": plans[key].curve}).items():
        if reading == "S_hat":  # eq. 6 removes all backscatter: without noise the contrast is 1 everywhere
            assert np.allclose(curve.objective_noise_free, 1.0)
        else:
            assert np.all(np.diff(curve.objective_noise_free) > 0), reading


@pytest.mark.parametrize("key,reading", [("flood", "E"), ("flood_polarized", "E_b"),
                                         ("flood_polarized", "S_hat")])
def test_fig8_sensor_noise_gives_an_interior_maximum_stable_under_refinement(fig8_flood, key, reading):
    coarse, plans, fine_plans = fig8_flood
    c = plans[key].readings.get(reading, plans[key].curve)
    f = fine_plans[key].readings.get(reading, fine_plans[key].curve)
    assert 0 < c.best_index < len(coarse) - 1
    assert 0 < f.best_index < len(f.separations_m) - 1
    assert c.objective[c.best_index] > c.objective[0] and c.objective[c.best_index] > c.objective[-1]
    assert np.all(c.objective <= c.objective_noise_free + 1e-12)
    assert abs(f.best_separation_m - c.best_separation_m) <= (coarse[1] - coarse[0]) + 1e-12


def test_bisection_rounds_refine_the_pick_between_the_grids_points(paper_geometry):
    """refine: the grid's points keep their values, each round adds the midpoints either side of a curve's
    best, and the best cannot get worse (the stripe composite ripples between grid points, planning.md §8)."""
    w, h = paper_geometry.camera.resolution
    model = SceneModel(paper_geometry, fidelity="preview", pixels=[[h // 2, w // 2]], orders="single")
    coarse = default_separations(8, 0.02, 0.6)
    grid = plan(model, coarse, modalities=("flood",), exposure="auto", refine=0)
    refined = plan(model, coarse, modalities=("flood",), exposure="auto", refine=2)
    step = coarse[1] - coarse[0]
    for key in ("flood", "flood_polarized"):
        for reading, c0 in (grid[key].readings or {"E": grid[key].curve}).items():
            c2 = (refined[key].readings or {"E": refined[key].curve})[reading]
            assert np.all(np.diff(c2.separations_m) > 0)
            on = np.isin(np.round(c2.separations_m, 9), np.round(coarse, 9))
            assert on.sum() == coarse.size
            np.testing.assert_array_equal(c2.objective[on], c0.objective)
            extra = np.round(c2.separations_m[~on], 9)
            i = c0.best_index
            first = [round(0.5 * (coarse[i] + coarse[j]), 9) for j in (i - 1, i + 1) if 0 <= j < coarse.size]
            assert set(first) <= set(extra.tolist()), reading
            assert 2 <= extra.size <= 2 * 2 * 3         # two rounds, at most two midpoints per curve's best
            assert np.all(np.abs(np.subtract.outer(extra, coarse)).min(axis=1) <= step / 2 + 1e-9)
            assert c2.objective.max() >= c0.objective.max()
            assert abs(c2.best_separation_m - c0.best_separation_m) <= step / 2 + step / 4 + 1e-9
    with pytest.raises(SceneError, match="refine"):
        plan(model, coarse, modalities=("flood",), refine=-1)


def test_no_bisection_toward_a_neighbour_that_saturates():
    """The midpoints either side of the best, but none toward a neighbour 1 cm or less away whose image loses
    more pixels to saturation than the best's (a cliff the prediction places only to ~0.5 cm, planning.md
    §8); a wider gap toward it is bisected (the coarse search's first rounds)."""
    from polarstripe.planning.objectives import Objective
    from polarstripe.planning.planner import _bisections

    def curve(quality, lost):
        objs = [Objective(np.array([q]), np.ones(1), np.array([False]), frame_quality=q, frame_lost=f)
                for q, f in zip(quality, lost, strict=True)]
        return {("E",): (objs, objs)}

    seps = [0.04, 0.01, 0.03, 0.02]              # in the order evaluated: bisections come last
    assert sorted(_bisections(seps, curve([0.6, 0.2, 0.9, 0.5], [0, 0, 0, 0]))) == [0.025, 0.035]
    assert _bisections(seps, curve([0.6, 0.2, 0.9, 0.5], [0, 0.9, 0, 0.01])) == [0.035]
    assert _bisections(seps, curve([0.6, 0.2, 0.9, 0.5], [0.2, 0, 0.1, 0.1])) == [0.025]
    assert _bisections([0.01, 0.02, 0.015], curve([0.2, 0.9, 0.5], [0, 0, 0])) == [0.0175]  # the nearest done
    # 10 cm apart: a saturating neighbour nearly as good (the optimum may sit at the cliff's edge) is
    # approached, one that loses far more is not; 1 cm apart neither is
    wide = [0.4, 0.1, 0.3, 0.2]
    assert sorted(_bisections(wide, curve([0.6, 0.2, 0.9, 0.88], [0, 0.9, 0, 0.01]))) == [0.25, 0.35]
    assert _bisections(wide, curve([0.6, 0.2, 0.9, 0.5], [0, 0.9, 0, 0.01])) == [0.35]
    assert _bisections(seps, curve([0.6, 0.2, 0.9, 0.88], [0, 0.9, 0, 0.01])) == [0.035]


def test_fig8_polarization_lies_above(fig8_flood):
    """Fig. 9a: the polarized curve lies above the unpolarized one, noise-free everywhere and at the best
    noisy value; the plan recommends the better polarized reading."""
    _, plans, _ = fig8_flood
    plain, pol = plans["flood"].curve, plans["flood_polarized"]
    eb = pol.readings["E_b"]
    assert np.all(eb.objective_noise_free >= plain.objective_noise_free)
    assert eb.objective.max() > plain.objective.max()
    best = max(pol.readings, key=lambda r: pol.readings[r].objective.max())
    assert pol.reading == best and pol.curve is pol.readings[best]
    assert pol.recommendation["reading"] == best and "noise" in pol.recommendation["reason"]


def test_recommendation_prefers_e_b_in_a_tie_and_says_why():
    seps = np.array([0.1, 0.2, 0.3])

    def curve(obj, q, w):
        return Curve(seps, np.array(obj), np.ones(3), np.array(q), np.array(w), np.zeros(3, bool))

    eb = curve([0.5, 0.6, 0.4], [0.7, 0.8, 0.9], [0.7, 0.75, 0.45])
    weak = curve([0.2, 0.3, 0.1], [1, 1, 1], [0.2, 0.3, 0.1])
    strong = curve([0.8, 0.9, 0.7], [1, 1, 1], [0.8, 0.9, 0.7])
    tie = curve([0.5, 0.605, 0.4], [1, 1, 1], [0.5, 0.605, 0.4])
    assert recommend_reading({"E_b": eb, "S_hat": weak}, 0.8)["reading"] == "E_b"
    rec = recommend_reading({"E_b": eb, "S_hat": strong}, 0.8)
    assert rec["reading"] == "S_hat" and "×2.3" in rec["reason"]  # sqrt(2(1 + 1/0.64)) = 2.26
    assert recommend_reading({"E_b": eb, "S_hat": tie}, 0.8)["reading"] == "E_b"


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
    assert set(doc["flood_polarized"]["readings"]) == {"E_b", "S_hat"}
    assert doc["flood_polarized"]["reading"] == doc["flood_polarized"]["recommendation"]["reading"]
    entry = doc["stripes_polarized"]
    assert entry["measure"] == "margin*W" and entry["edge"] == "margin" and entry["reading"] == "E_b"
    assert len(entry["locations"][0]["limited_by"]) == 6
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
    s = Samples(np.array([1.0]), np.array([0.0]), np.array([0.0]), np.array([0.8]))
    with pytest.raises(SceneError, match="reading"):
        objective(s, IDEAL_SENSOR, modality="stripes", reading="S_hat")
    with pytest.raises(SceneError, match="competitors"):
        objective(s, IDEAL_SENSOR, modality="stripes", reading="E")


def test_plan_command_json_and_plot(tmp_path):
    png = tmp_path / "plan.png"
    out = subprocess.run([sys.executable, "-m", "polarstripe", "plan", "--modality", "flood", "--json",
                          "--separations", "5", "--fidelity", "preview", "--width", "96", "--plot", str(png)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    jsonschema.validate(doc, PLAN_SCHEMA)
    assert set(doc) == {"flood", "flood_polarized", "model", "search", "reference", "scans", "figure"}
    # the evaluations the search made: each reading's curve holds them all
    assert doc["search"]["evaluations"] == {"flood": len(doc["flood"]["separations"])} and \
        doc["search"]["separations"] == 5 and len(doc["flood"]["separations"]) > 5
    assert set(doc["reference"]["plans"]) == {"flood", "flood_polarized"} and doc["scans"] == []
    assert png.stat().st_size > 10_000


def test_plan_command_bad_scene_is_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[medium]\nsigma_t = -1\n")
    out = subprocess.run([sys.executable, "-m", "polarstripe", "plan", str(bad)], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 2 and "sigma_t" in out.stderr and "Traceback" not in out.stderr


def _competitor_max(samples, polarized=False):
    c = samples.competitors
    p = np.clip(c.dop, 0.05, 1.0) if polarized else 0.0
    return (c.direct + c.indirect + c.backscatter * (1.0 - p)).max(axis=1)


def test_margin_is_eq9_in_a_medium_without_backscatter():
    """albedo 0 (sigma_s = 0): no A, no B anywhere, so the margin and eq. 9 are both D/D = 1 wherever O is
    lit, at every separation; W still falls with the attenuation of D (sigma_t = 6)."""
    scene = load_scene(None)
    scene = scene.replace(medium=scene.medium.replace(sigma_t=6.0, albedo=0.0))
    seps = default_separations(5, 0.02, 0.6)
    margin = plan(SceneModel(scene, fidelity="preview"), seps, modalities=("stripes",))
    eq9 = plan(SceneModel(scene, fidelity="preview", edge="eq9"), seps, modalities=("stripes",))
    for key in ("stripes", "stripes_polarized"):
        for cm, ce in zip(margin[key].location_curves, eq9[key].location_curves, strict=True):
            np.testing.assert_allclose(cm.quality, 1.0)
            np.testing.assert_allclose(ce.quality, 1.0)
            np.testing.assert_allclose(cm.objective, ce.objective)


def test_margin_competitors_match_a_brute_force_scan():
    """The planner evaluates only B (and its DOP) of the sheets that cross O's ray, plus O's unlit
    neighbours; brute force renders O under every stripe of the rotate scan with D, A and B and drops the
    stripe that lights O. The brightest competitor agrees to 2 %."""
    scene = load_scene(None)
    scene = scene.replace(medium=scene.medium.replace(sigma_t=6.0))
    model = SceneModel(scene, fidelity="preview")
    for d in (0.06, 0.2):
        s = model.stripes(d)
        sd = with_separation(scene, d)
        full = np.zeros((30, 3))
        for k in range(30):
            r = render_components(sd, f"stripe:{k}/30", "preview", model.pixels, orders=model.orders)
            full[k] = np.where(r.D > 0, 0.0, r.D + r.A + r.B)  # the stripe that lights O is its own
        c = s.competitors
        neighbours = (c.direct + c.indirect + c.backscatter)[:, :2].max(axis=1)
        brute = np.maximum(full.max(axis=0), neighbours)
        np.testing.assert_allclose(_competitor_max(s), brute, rtol=0.02)


def test_neighbours_are_the_nearest_unlit_pixels():
    """O' (left and right) is the first pixel off the lit run of O's sheet, or the next one when the first
    is only partly lit: found independently from D along O's row under the same sheet."""
    scene = load_scene(None)
    w, h = scene.camera.resolution
    model = SceneModel(scene, fidelity="preview", pixels=[[h // 2, w // 2]])
    for d in (0.05, 0.4):
        sd = with_separation(scene, d)
        base = sd.projector
        tan_half = math.tan(math.radians(base.fov_deg) / 2.0)
        pitch = 2.0 * tan_half / 30
        rows = max(3, round(base.resolution[1] * 2.0 * tan_half / base.resolution[0] / pitch))
        proj = base.replace(look_at=tuple(model.points[0]), resolution=(3, rows),
                            fov_deg=math.degrees(2.0 * math.atan(1.5 * pitch)))
        row = np.stack([np.full(w, h // 2), np.arange(w)], axis=1)
        lit = render_components(sd.replace(projector=proj), "stripe:1/3", "preview", row, need=("D",)).D > 0
        run = np.nonzero(~lit[: w // 2])[0][-1], w // 2 + np.nonzero(~lit[w // 2:])[0][0]
        sides = dict(model._neighbours(part_frame(proj), 0))
        assert sides[0][1] in (run[0], run[0] - 1) and sides[1][1] in (run[1], run[1] + 1)


def test_margin_rejects_the_colocated_source_that_eq9_prefers():
    """Issue: eq. 9 counts the sheet's own backscatter as edge signal, so on the default tank at
    sigma_t = 6 its stripe optimum is the smallest separation. Near the camera the other sheets'
    backscatter outshines O (Fig. 7): the margin there is 0 and its optimum lies inside the range."""
    scene = load_scene(None)
    scene = scene.replace(medium=scene.medium.replace(sigma_t=6.0))
    seps = np.array([0.01, 0.03, 0.1, 0.2, 0.35, 0.5])
    # the margin as derived (docs/planning.md §1), on the paper's single-scattering model: with all orders
    # its optimum moves to the range's far end, which the end-to-end truth does not support (§7)
    eq9 = plan(SceneModel(scene, fidelity="preview", edge="eq9", orders="single"), seps,
               modalities=("stripes",))
    margin = plan(SceneModel(scene, fidelity="preview", orders="single"), seps, modalities=("stripes",))
    for key in ("stripes", "stripes_polarized"):
        assert eq9[key].curve.best_separation_m <= 0.03
        m = margin[key]
        assert m.curve.objective[0] == 0.0 and 0 < m.curve.best_index < len(seps) - 1
        assert all(c.limited_by[0] == "sheet" for c in m.location_curves)
        assert all(c.limited_by[-1] == "neighbour" for c in m.location_curves)
    # the polarizer filters the sheets' backscatter: the margin is never lower with it
    for cu, cp in zip(margin["stripes"].location_curves, margin["stripes_polarized"].location_curves,
                      strict=True):
        assert np.all(cp.quality >= cu.quality - 1e-9)
    with pytest.raises(SceneError, match="edge"):
        SceneModel(scene, edge="gradient")
