"""``polarstripe plan`` (planning/plan_cli.py) on a small real plan (preview fidelity, 4 separations, 2
stripe locations): the JSON (plain types, each entry's best separation is its objective's argmax, the
measure per modality, PLAN_SCHEMA's refusals), the printed tables, the plot's panels, and the command's
argument errors as one line. (test_planner.py runs the planner itself and the command end to end.)"""

from __future__ import annotations

import copy
import json
import struct
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from polarstripe.planning.plan_cli import PLAN_SCHEMA, _print_tables, plan_to_json
from polarstripe.planning.plan_plot import draw_figure, figure_data
from polarstripe.planning.planner import SceneModel, default_separations, plan
from polarstripe.sim.scene import load_scene
from polarstripe.tools.cli import main


@pytest.fixture(scope="module")
def plans():
    scene = load_scene(None)
    w, h = scene.camera.resolution
    pixels = [[h // 2, w // 4], [h // 2, w // 2]]
    model = SceneModel(scene, fidelity="preview", pixels=pixels)
    return plan(model, default_separations(4, 0.05, 0.5))


@pytest.fixture
def doc(plans):
    return plan_to_json(plans)


def test_json_has_one_entry_per_plan_with_its_best_separation(plans, doc):
    assert list(doc) == list(plans) == ["flood", "flood_polarized", "stripes", "stripes_polarized"]
    for key, entry in doc.items():
        assert entry["modality"] == key.split("_")[0] and entry["polarized"] == key.endswith("_polarized")
        assert entry["separations"] == pytest.approx([0.05, 0.2, 0.35, 0.5])
        assert entry["best_separation"] == entry["separations"][int(np.argmax(entry["objective"]))]
        assert len(entry["objective"]) == len(entry["objective_noise_free"]) == len(entry["saturated"]) == 4
        assert entry["exposure_scale"] > 0
    assert doc["flood"]["measure"] == doc["flood_polarized"]["measure"] == "CQM*W"
    assert doc["stripes"]["measure"] == doc["stripes_polarized"]["measure"] != "CQM*W"
    for key in ("stripes", "stripes_polarized"):
        locations = doc[key]["locations"]
        assert len(locations) == 2 and all(len(loc["pixel"]) == 2 for loc in locations)
        for loc in locations:
            assert loc["best_separation"] == loc["separations"][int(np.argmax(loc["objective"]))]
        scan = doc[key]["scan"]
        assert scan["winner"] in ("rotate", "translate", "both")
        assert scan["scores"][scan["winner"]] is not None
    assert "locations" not in doc["flood"] and "scan" not in doc["flood"]


def test_json_is_plain_and_valid(doc):
    text = json.dumps(doc)  # no numpy types left
    assert json.loads(text) == doc
    assert all(type(x) is bool for x in doc["flood"]["saturated"])
    jsonschema.Draft202012Validator.check_schema(PLAN_SCHEMA)
    jsonschema.validate(doc, PLAN_SCHEMA)
    jsonschema.validate({k: doc[k] for k in ("flood", "flood_polarized")}, PLAN_SCHEMA)


def _break(doc, path, value=None, delete=False):
    d = copy.deepcopy(doc)
    *head, last = path
    where = d
    for k in head:
        where = where[k]
    if delete:
        del where[last]
    else:
        where[last] = value
    return d


@pytest.mark.parametrize(
    "path, value, delete",
    [
        (("flood", "objective_noise_free"), None, True),
        (("stripes", "scan"), None, True),
        (("stripes", "locations"), [], False),
        (("stripes", "scan", "winner"), "teleport", False),
        (("stripes", "scan", "scores", "both"), None, True),
        (("stripes", "locations", 0, "pixel"), [1, 2, 3], False),
        (("flood", "separations"), [0.1], False),
        (("flood", "saturated"), [0, 1, 0], False),
        (("flood", "modality"), "laser", False),
        (("flood", "exposure_scale"), 0, False),
        (("laser",), {}, False),
    ],
    ids=lambda v: "/".join(map(str, v)) if isinstance(v, tuple) else None,
)
def test_the_schema_refuses_a_broken_plan(doc, path, value, delete):
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(_break(doc, path, value, delete), PLAN_SCHEMA)


def test_the_schema_refuses_an_empty_plan():
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({}, PLAN_SCHEMA)


def test_tables(doc, capsys):
    _print_tables(doc)
    out = capsys.readouterr().out.splitlines()
    for modality in ("flood", "stripes"):
        head = next(i for i, line in enumerate(out) if line.startswith(f"{modality}: "))
        plain, pol = doc[modality], doc[modality + "_polarized"]
        best = out[head + 1]
        assert best.startswith(f"  best d_LC = {plain['best_separation'] * 100:.1f} cm without a polarizer (")
        assert f", {pol['best_separation'] * 100:.1f} cm with one (" in best
        rows = [line.split() for line in out[head:] if line[:11].strip().replace(".", "").isdigit()][:4]
        assert [float(r[0]) for r in rows] == pytest.approx([5.0, 20.0, 35.0, 50.0])
        assert [float(r[1]) for r in rows] == pytest.approx(plain["objective"], abs=1e-4)  # first column: E
    assert out[0].startswith("flood: ")


def test_tables_flag_saturated_rows(doc, capsys):
    d = copy.deepcopy(doc)
    d["flood"]["saturated"] = [False, True, False, False]
    _print_tables({k: d[k] for k in ("flood", "flood_polarized")})
    out = capsys.readouterr().out.splitlines()
    rows = [line for line in out if line[:11].strip().replace(".", "").isdigit()]
    assert len(rows) == 4 and rows[1].endswith(" saturated")


def _png_size(path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def test_plot_has_one_panel_per_figure(doc, tmp_path):
    both, flood = tmp_path / "both.png", tmp_path / "flood.png"
    draw_figure(figure_data(doc), str(both))
    draw_figure(figure_data({k: doc[k] for k in ("flood", "flood_polarized")}), str(flood))
    (w3, h3), (w1, h1) = _png_size(both), _png_size(flood)
    assert h3 == h1 and w3 == pytest.approx(3 * w1, abs=2)  # flood, stripes, polarized stripes
    assert both.stat().st_size > flood.stat().st_size > 10_000


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--separations", "1"], "separations: need n >= 2 and 0 < d_min < d_max, got n=1"),
        (["--range", "0.5", "0.1"], "got n=20, d_min=0.5, d_max=0.1"),
        (["--range", "0", "0.5"], "d_min=0.0"),
        (["--fidelity", "bogus"], "fidelity 'bogus' is not preview, standard, reference"),
        (["/nonexistent/scene.toml"], "/nonexistent/scene.toml"),
    ],
)
def test_bad_arguments_are_one_error_line(argv, needle, capsys):
    assert main(["plan", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("polarstripe plan: error: ") and needle in err[0]


@pytest.mark.parametrize(
    "argv, needle",
    [(["--modality", "laser"], "invalid choice: 'laser'"), (["--exposure", "max"], "invalid choice: 'max'"),
     (["--edge", "sobel"], "invalid choice: 'sobel'"), (["--range", "0.1"], "expected 2 arguments"),
     (["--k-detect", "three"], "invalid float value: 'three'")],
)
def test_usage_errors(argv, needle, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["plan", *argv])
    assert exc.value.code == 2 and needle in capsys.readouterr().err


def test_a_frame_budget_plans_sheets_only_where_they_stay_apart(capsys):
    """30 stripes in 4 frames of a polarized scan: 15 sheets per frame, 1 stripe (34 projector columns) apart,
    which only the narrowest baseline keeps apart over the chart's depth range (planning/sheets.py): the pick
    is there, the other separations score 0."""
    assert main(["plan", "--modality", "stripes", "--separations", "3", "--range", "0.05", "0.3",
                 "--stripes", "30", "--max-frames", "4", "--width", "96", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    jsonschema.validate(doc, PLAN_SCHEMA)
    allowed = doc["sheets"].pop("allowed")     # per separation of the curves: the grid and its bisections
    assert doc["sheets"] == {"sheets": 15, "max_frames": 4, "analyzer": "stage", "frames": 4}
    seps = np.array(doc["stripes"]["separations"])
    assert len(allowed) == seps.size and allowed[0] and not any(np.array(allowed)[seps >= 0.175])
    for key in ("stripes", "stripes_polarized"):
        assert doc[key]["separations"] == doc["stripes"]["separations"]
        obj = np.array(doc[key]["objective"])
        assert doc[key]["best_separation"] < 0.175 and obj[0] > 0
        assert np.all(obj[~np.array(allowed)] == 0.0)


@pytest.mark.parametrize("extra, width", [([], 128), (["--width", "100"], 100)])
def test_the_error_measure_renders_at_the_scene_cameras_width(tmp_path, capsys, extra, width):
    """A stripe composite aliases on the camera's pixel grid (docs/planning.md §8): by default the plan
    renders at the scene camera's width, 128 px here (under 10 px per stripe); --width asks for another."""
    scene = tmp_path / "small.toml"
    chart = Path(__file__).parents[2] / "bench" / "scenes" / "tank_sigma5.toml"
    scene.write_text(chart.read_text() + "\n[camera]\nresolution = [128, 96]\n")
    assert main(["plan", str(scene), "--modality", "flood", "--separations", "2", "--range", "0.1", "0.3",
                 "--stripes", "16", *extra, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    jsonschema.validate(doc, PLAN_SCHEMA)
    assert doc["model"] == {"measure": "error", "orders": "all", "width": width}


def test_a_width_below_eight_pixels_is_one_error_line(capsys):
    assert main(["plan", "--modality", "flood", "--separations", "2", "--width", "4"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "width must be an integer of at least 8 pixels, got 4" in err[0]
