"""``polarstripe plan --plot`` (planning/plan_plot.py): the plotted data are the curves of plans computed
independently through the planner's API (the plan's measure with all orders, the paper's with single
scattering), normalised by hand; Fig. 10's answer is compare_scans' on those plans; the end-to-end points
appear only with --validate and are the validation's own rows; a bad --plot path is one line, exit 2."""

from __future__ import annotations

import contextlib
import io
import json
import struct

import jsonschema
import numpy as np
import pytest
from polarstripe.planning.image_model import ImageModel
from polarstripe.planning.plan_cli import PLAN_SCHEMA
from polarstripe.planning.plan_plot import figure_data
from polarstripe.planning.planner import SEARCHES, SceneModel, default_separations, plan
from polarstripe.sim.scene import load_scene
from polarstripe.tools.cli import main

SEPS = (3, 0.05, 0.45)   # separations: n, min, max [m]
WIDTH = 48               # the error measure's renders (the camera's 640 px by default: much slower)
SMALL = ["--separations", str(SEPS[0]), "--range", str(SEPS[1]), str(SEPS[2]), "--fidelity", "preview",
         "--width", str(WIDTH), "--stripes", "8"]


def _run(argv: list[str]) -> dict:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["plan", *argv, "--json"]) == 0
    return json.loads(out.getvalue())


@pytest.fixture(scope="module")
def drawn(tmp_path_factory):
    png = tmp_path_factory.mktemp("plot") / "plan.png"
    return _run([*SMALL, "--plot", str(png)]), png


@pytest.fixture(scope="module")
def independent():
    """The two plans made directly, not through the command (with its bisections around each best)."""
    scene, seps = load_scene(None), default_separations(*SEPS)
    kw = dict(refine=SEARCHES["coarse"].refine, rivals=SEARCHES["coarse"].rivals)   # the command's search
    return {"plan": plan(ImageModel(scene, fidelity="preview", n_stripes=8, orders="all", width=WIDTH), seps,
                         **kw),
            "reference": plan(SceneModel(scene, fidelity="preview", n_stripes=8, orders="single"), seps,
                              **kw)}


def _panel(doc, key):
    return next(p for p in doc["figure"]["panels"] if p["key"] == key)


def test_the_plotted_curves_are_the_plans_normalised(drawn, independent):
    doc, _ = drawn
    jsonschema.validate(doc, PLAN_SCHEMA)
    assert [p["key"] for p in doc["figure"]["panels"]] == ["flood", "stripes", "stripes_polarized"]
    for role, plans in independent.items():
        flood = [plans[k].curve.objective for k in ("flood", "flood_polarized")]
        seps_cm = plans["flood"].curve.separations_m * 100      # the grid and its bisections
        top = max(c.max() for c in flood)
        drawn_flood = [c for c in _panel(doc, "flood")["curves"] if c["model"] == role]
        assert len(drawn_flood) == 2
        for c, want in zip(drawn_flood, flood, strict=True):
            assert c["separations_cm"] == pytest.approx(seps_cm)
            assert c["values"] == pytest.approx(want / top, rel=1e-9)
            assert c["pick_cm"] == pytest.approx(seps_cm[np.argmax(want)])
        assert max(max(c["values"]) for c in drawn_flood) == pytest.approx(1.0)
        # stripes: O1..O3 and their mean, one normaliser over both stripe plans' locations
        top = max(lc.objective.max() for k in ("stripes", "stripes_polarized")
                  for lc in plans[k].location_curves)
        seps_cm = plans["stripes"].curve.separations_m * 100
        for key in ("stripes", "stripes_polarized"):
            curves = [c for c in _panel(doc, key)["curves"] if c["model"] == role]
            want = [lc.objective for lc in plans[key].location_curves] + [plans[key].curve.objective]
            assert [c["location"] for c in curves] == [0, 1, 2, None]
            for c, w in zip(curves, want, strict=True):
                assert c["values"] == pytest.approx(w / top, rel=1e-9)
                assert c["pick_cm"] == pytest.approx(seps_cm[np.argmax(w)])
    # the plan's own measure is not the paper's: the two models' curves differ
    grid = np.round(default_separations(*SEPS) * 100, 6)            # the points both models evaluated
    e = [np.asarray(c["values"])[np.isin(np.round(c["separations_cm"], 6), grid)]
         for c in _panel(doc, "flood")["curves"] if c["label"].startswith("E,")]
    assert len(e) == 2 and e[0].size == e[1].size == grid.size and not np.allclose(e[0], e[1], atol=1e-3)


def test_fig10_answer_is_compare_scans_for_both_models(drawn, independent, capsys):
    doc, _ = drawn
    rows = {(r["plan"], r["model"]): r for r in doc["scans"]}
    assert set(rows) == {(k, m) for k in ("stripes", "stripes_polarized") for m in ("plan", "reference")}
    for (key, role), row in rows.items():
        scan = independent[role][key].scan
        assert row["winner"] == scan["winner"]
        assert row["scores"] == pytest.approx(scan["scores"], rel=1e-9)
        assert row in _panel(doc, key)["scans"]
    assert rows[("stripes", "reference")]["label"] == "margin*W, single scattering"
    assert rows[("stripes", "plan")]["label"] == "1-error, all orders"


def test_no_end_to_end_points_without_validate(drawn):
    doc, png = drawn
    assert "validation" not in doc
    assert all(p["e2e"] == [] for p in doc["figure"]["panels"])
    head = png.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    width, _ = struct.unpack(">II", head[16:24])
    assert width == pytest.approx(3 * 6.4 * 120, abs=2)  # one panel per figure of the paper (3)


def test_end_to_end_points_are_the_validations_rows():
    """figure_data on hand-made validation rows: grid and off-grid rows merged in order, a missing error left
    out, the best the least error."""
    doc = {"flood": {"separations": [0.1, 0.2], "objective": [0.5, 1.0], "reading": "E", "measure": "m"},
           "model": {"measure": "error", "orders": "all"},
           "validation": {"curves": {"flood": [{"separation_m": 0.3, "error": 0.4},
                                               {"separation_m": 0.1, "error": 0.6}],
                                     "polarized_flood": [{"separation_m": 0.1, "error": None,
                                                          "error_e_b": 0.5}]},
                          "extra": {"flood": [{"separation_m": 0.2, "error": 0.35}]}}}
    (panel,) = figure_data(doc)["panels"]
    pts = {(p["method"], p["image"]): p for p in panel["e2e"]}
    assert set(pts) == {("flood", "error"), ("polarized_flood", "error_e_b")}
    assert pts["flood", "error"]["separations_cm"] == pytest.approx([10, 20, 30])
    assert pts["flood", "error"]["error"] == [0.6, 0.35, 0.4] and pts["flood", "error"]["best_cm"] == 20
    assert not pts["flood", "error"]["best_at_edge"] and pts["polarized_flood", "error_e_b"]["best_at_edge"]
    curve = panel["curves"][0]
    assert curve["values"] == [0.5, 1.0] and curve["pick_cm"] == 20 and curve["pick_at_edge"]
    del doc["validation"]
    assert figure_data(doc)["panels"][0]["e2e"] == []


def test_validate_draws_the_end_to_end_points(tmp_path):
    doc = _run([*SMALL, "--modality", "flood", "--validate", "--validate-grid", "2", "--validate-width", "24",
                "--plot", str(tmp_path / "v.png")])
    (panel,) = doc["figure"]["panels"]
    v = doc["validation"]
    for p in panel["e2e"]:
        rows = sorted(v["curves"][p["method"]] + v["extra"][p["method"]], key=lambda r: r["separation_m"])
        assert p["separations_cm"] == pytest.approx([r["separation_m"] * 100 for r in rows])
        assert p["error"] == [r[p["image"]] for r in rows]
    assert {(p["method"], p["image"]) for p in panel["e2e"]} == {
        ("flood", "error"), ("polarized_flood", "error"), ("polarized_flood", "error_e_b")}
    # both models' picks are judged
    assert {r["plan"] for r in v["rows"]} == {"error", "single"}
    assert (tmp_path / "v.png").stat().st_size > 10_000


@pytest.mark.parametrize("where, needle", [
    ("{tmp}/missing/plan.png", "does not exist"),
    ("{tmp}/plan.txt", "must end in .png, .pdf, .svg"),
    ("{tmp}/folder.png", "is a folder"),
])
def test_a_bad_plot_path_is_one_line_before_any_work(tmp_path, capsys, where, needle):
    (tmp_path / "folder.png").mkdir()
    assert main(["plan", "--plot", where.format(tmp=tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("polarstripe plan: error: --plot: ") and needle in err[0]


def test_the_papers_sweep_is_made_only_when_asked():
    """The comparison costs a second sweep: a plain ``plan`` does not make it, ``--reference`` does."""
    plain = _run(SMALL)
    assert "reference" not in plain and {r["model"] for r in plain["scans"]} <= {"plan"}
    asked = _run([*SMALL, "--reference"])
    assert asked["reference"]["orders"] == "single" and {r["model"] for r in asked["scans"]} == {
        "plan", "reference"}
