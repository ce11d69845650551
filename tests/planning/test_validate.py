"""The end-to-end truth of plans (planning/validate.py, planning/validate_table.py): full scans through the
compositor's pipeline, checked against the sensor's closed-form noise in clear water, and the regret table's
bookkeeping against hand-made curves."""

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest
from polarstripe.planning.validate import ScanSettings, curves, scan_scene
from polarstripe.planning.validate_table import _bisections, default_grid, regret_rows, validate
from polarstripe.sim.geometry import intersect, pinhole_frame, pixel_rays
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import SceneError, load_scene, with_separation

TINY = ScanSettings(fidelity="preview", n_stripes=4, width=32, exposure="method")


@pytest.fixture(scope="module")
def tank():
    return load_scene(None)


def _noise_limited_error(scene, exposure_scale: float) -> float:
    """‖noise‖ / ‖T‖ in DN when the image is T itself: EMVA 1288 by hand (docs/physics.md §7): per pixel
    μ_e = L·η·(π a²/4)·s²·cos⁴α·t/(hc/λ), σ² = (σ_r² + μ_e + μ_dark)/K² + 1/12 [DN²]."""
    cam = scene.camera
    t = cam.exposure_s * exposure_scale
    fr = pinhole_frame(cam.position, cam.look_at, cam.up, cam.fov_deg, cam.resolution)
    dirs = pixel_rays(fr)
    cos_a = dirs @ fr.f
    hits = intersect(scene.objects, fr.position, dirs)
    lit = np.isfinite(hits.t)
    # T in clear water: rho cos(phi)/pi * I0 / d_LO^2 (no attenuation; the source's radius is 1 mm)
    src = np.asarray(scene.projector.position)
    to_src = src - hits.point[lit]
    d2 = np.sum(to_src ** 2, axis=1)
    cos_phi = np.clip(np.sum(to_src * hits.normal[lit], axis=1) / np.sqrt(d2), 0.0, None)
    radiance = np.zeros(dirs.shape[0])
    radiance[lit] = 0.6 / math.pi * cos_phi * scene.projector.intensity_w_sr / (
        d2 + scene.projector.source_radius_m ** 2)
    photon = 6.62607015e-34 * 299792458.0 / (cam.wavelength_nm * 1e-9)
    mu_e = radiance * cam.qe * math.pi * cam.aperture_m ** 2 / 4 * fr.s ** 2 * cos_a ** 4 * t / photon
    var_dn = (cam.read_noise_e ** 2 + mu_e + cam.dark_current_e_s * t) / cam.gain_e_per_dn ** 2 + 1 / 12
    return float(np.sqrt(var_dn.sum()) / np.linalg.norm(mu_e / cam.gain_e_per_dn))


def test_clear_water_every_composite_is_the_object_up_to_sensor_noise(tank):
    """With sigma_t = 0 the frames hold T (no A, no B): the flood frame, the stripe max (eq. 7) and the
    polarized flood (no backscatter: the model's p map is not used) differ from T by the sensor's noise
    alone."""
    clear = tank.replace(medium=tank.medium.replace(sigma_t=0.0))
    got = curves(clear, [0.1], TINY, methods=("flood", "stripes", "polarized_flood"))
    small = scan_scene(clear, TINY.width)
    sd = with_separation(small, 0.1)
    for method in ("flood", "stripes", "polarized_flood"):
        row = got[method][0]
        predicted = _noise_limited_error(sd, row["exposure_scale"] * (0.5 if "polarized" in method else 1))
        assert row["saturated_fraction"] == 0.0
        assert row["error"] == pytest.approx(predicted, rel=0.3), method
    # no backscatter: the model's map has nothing to fit (the frames' map or none stands in)
    assert "0 pixels with backscatter in the model" in got["polarized_flood"][0]["note"]
    assert got["stripes"][0]["depth_valid_fraction"] > 0.5
    assert got["stripes"][0]["depth_rms_mm"] < 20.0


def test_murky_water_stripes_beat_flood_and_polarization_helps(tank):
    """At sigma_t = 5 /m the flood carries all the backscatter; the stripe composite (eq. 7) removes most of
    it and eq. 6 more (the paper's Fig. 6 ordering), at a mid separation."""
    got = curves(tank, [0.15], TINY)
    err = {m: rows[0]["error"] for m, rows in got.items()}
    assert err["stripes"] < err["flood"]
    assert err["polarized_flood"] < err["flood"]
    assert err["polarized_stripes"] < err["stripes"]
    assert got["polarized_flood"][0]["error_e_b"] < err["flood"]
    assert 0.0 < got["polarized_flood"][0]["p"] <= 1.0
    # eq. 6 by the compositor's default, the model's map (fitted to the flood pair): the medium's DOP it
    # reports is the backscatter's own, Σ p B / Σ B of the scene's render at the scan's pose
    sd = with_separation(scan_scene(tank, TINY.width), 0.15, aim=True)
    c = render_components(sd, "flood", TINY.fidelity)
    p_true = float(np.sum(c.p * c.B) / np.sum(c.B))
    for m in ("polarized_flood", "polarized_stripes"):
        assert "note" not in got[m][0], got[m][0].get("note")
        assert got[m][0]["p"] == pytest.approx(p_true, abs=0.05), m
    median = curves(tank, [0.15], dataclasses.replace(TINY, p_rule="median"), methods=("polarized_flood",))
    assert median["polarized_flood"][0]["p"] < p_true - 0.05  # the ratio of medians reads p B/(S + B), low
    # the stripe scan's map is fitted to the polarized flood's pair, made from its own noise stream: the
    # row does not depend on whether the flood was scanned beside it
    alone = curves(tank, [0.15], TINY, methods=("polarized_stripes",))["polarized_stripes"][0]
    assert alone == got["polarized_stripes"][0]


class _Store:
    def __init__(self):
        self.rows = {}

    def get(self, key):
        return self.rows.get(key)

    def put(self, key, row):
        self.rows[key] = row


def test_validate_regret_is_at_least_one_and_best_is_the_minimum(tank):
    grid = [0.03, 0.1, 0.3]
    store = _Store()
    kw = dict(plan_orders=("single",), plan_fidelity="preview", n_plan=6, cache=store)
    res = validate(tank, grid, TINY, **kw)
    assert res["cached"] == 0 and res["scanned"] == len(store.rows) >= 3 * 4
    # a second run takes every scan from the cache and gives the same table; a row does not depend on the
    # methods scanned beside it (each has its own noise stream)
    again = validate(tank, grid, TINY, **kw)
    assert again["scanned"] == 0 and again["cached"] == res["scanned"] and again["rows"] == res["rows"]
    alone = curves(tank, [0.1], TINY, methods=("stripes",))["stripes"][0]
    assert alone == res["curves"]["stripes"][1]
    scored = {m: res["curves"][m] + res["extra"][m] for m in res["curves"]}
    for row in res["rows"]:
        key = "error" if row["image"] == "composite" else "error_e_b"
        errs = {r["separation_m"]: r[key] for r in scored[row["method"]]}
        assert row["best_error"] == min(errs.values())
        assert errs[row["best_m"]] == row["best_error"]
        assert row["pick_error"] == errs[min(errs, key=lambda d: abs(d - row["pick_m"]))]
        assert row["regret"] >= 1.0
        assert row["regret"] == pytest.approx(row["pick_error"] / row["best_error"])
        assert row["best_at_edge"] == (row["best_m"] <= grid[0] or row["best_m"] >= grid[-1])


def test_regret_rows_by_hand():
    grid = [0.02, 0.1, 0.6]
    curve = {0.02: 0.9, 0.1: 0.4, 0.6: 0.7, 0.2: 0.5}
    at = {m: {d: {"error": e, "error_e_b": e + 0.1} for d, e in curve.items()}
          for m in ("flood", "polarized_flood", "stripes", "polarized_stripes")}
    picks = {"x": {k: {"separation_m": 0.2, "at_edge": False, "reading": "E", "readings": {}}
                   for k in ("flood", "flood_polarized", "stripes", "stripes_polarized")}}
    picks["x"]["stripes"]["separation_m"] = 0.6
    picks["x"]["stripes"]["at_edge"] = True
    rows = {(r["method"], r["image"]): r for r in regret_rows(at, grid, picks)}
    assert rows[("flood", "composite")]["regret"] == pytest.approx(0.5 / 0.4)
    assert rows[("flood", "composite")]["best_m"] == 0.1
    assert rows[("flood", "composite")]["best_at_edge"] is False
    assert rows[("stripes", "composite")]["regret"] == pytest.approx(0.7 / 0.4)
    assert rows[("stripes", "composite")]["pick_at_edge"] is True
    assert rows[("polarized_stripes", "E_b")]["regret"] == pytest.approx(0.6 / 0.5)
    at["flood"] = {0.02: {"error": 0.3}, 0.1: {"error": 0.4}}  # best at the grid's end; the pick unscored
    rows = {(r["method"], r["image"]): r for r in regret_rows(at, grid, picks)}
    assert rows[("flood", "composite")]["best_at_edge"] is True
    flood = rows[("flood", "composite")]
    assert flood["pick_error"] is None and flood["regret"] is None


def test_bisection_scans_either_side_of_the_best():
    scored = {0.02: {"error": 0.5}, 0.08: {"error": 0.3}, 0.32: {"error": 0.4}, 0.5: {"error": None}}
    assert _bisections(scored, "error") == pytest.approx([0.04, 0.16])
    assert _bisections({0.02: {"error": 0.1}, 0.08: {"error": 0.3}}, "error") == pytest.approx([0.04])
    assert _bisections({0.02: {"error": 0.1}}, "error") == []


def test_bad_settings_are_one_line_errors(tank):
    with pytest.raises(SceneError, match="exposure must be one of"):
        curves(tank, [0.1], ScanSettings(exposure="bright"))
    with pytest.raises(SceneError, match="stripes must be"):
        curves(tank, [0.1], ScanSettings(n_stripes=1))
    with pytest.raises(SceneError, match="positive separations"):
        curves(tank, [-0.1], TINY)
    with pytest.raises(SceneError, match="grid"):
        default_grid(1)
    assert default_grid(3, 0.02, 0.5).tolist() == pytest.approx([0.02, 0.1, 0.5])


def test_bench_end_to_end_unknown_scene_is_one_line():
    r = subprocess.run([sys.executable, "-m", "polarstripe", "bench", "planner", "--end-to-end", "--scenes",
                        "no_such_scene"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "no_such_scene" in r.stderr and "Traceback" not in r.stderr


def test_scan_cache_keeps_rows_across_runs_per_code_version(tmp_path):
    from polarstripe.bench.planner_e2e import ScanCache, code_hash

    cache = ScanCache(str(tmp_path))
    assert cache.get("k") is None
    cache.put("k", {"error": 0.25})
    cache.save()
    assert cache.path.name == f"scans-{code_hash()}.json" and len(code_hash()) == 16
    assert ScanCache(str(tmp_path)).get("k") == {"error": 0.25}
    cache.path.write_text("{not json")  # a broken file is a cold cache, not an error
    assert ScanCache(str(tmp_path)).get("k") is None


def test_plan_validate_judges_the_plans_own_picks(capsys):
    import json

    import jsonschema
    from polarstripe.planning.plan_cli import PLAN_SCHEMA, _print_validation

    args = ["plan", "--modality", "flood", "--separations", "4", "--fidelity", "preview", "--validate",
            "--validate-grid", "2", "--stripes", "4", "--width", "32", "--json"]
    r = subprocess.run([sys.executable, "-m", "polarstripe", *args], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    jsonschema.validate(doc, PLAN_SCHEMA)
    v = doc["validation"]
    assert v["settings"]["width"] == doc["model"]["width"] == 32  # judged on the pixel grid it planned on
    assert set(v["curves"]) == {"flood", "polarized_flood"}  # no stripe plan: no stripe scans
    assert {(row["method"], row["image"]) for row in v["rows"]} == {
        ("flood", "composite"), ("polarized_flood", "composite"), ("polarized_flood", "E_b")}
    flood = next(row for row in v["rows"] if row["method"] == "flood")
    assert flood["pick_m"] == doc["flood"]["best_separation"] and flood["regret"] >= 1.0
    _print_validation(v)
    assert "polarized_flood" in capsys.readouterr().out
