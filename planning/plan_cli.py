"""``polarstripe plan SCENE.toml``: the best camera–source separation and stripe scan for a scene.

Prints the optimum and the curve per modality (default: 1 − the expected error; ``--measure paper``: flood
CQM·W, stripes margin·W), with and without a polarizer; ``--json`` prints one object keyed ``flood``,
``flood_polarized``, ``stripes``, ``stripes_polarized``, ``model`` (measure, orders and, for the error
measure, the renders' ``width``: the scene camera's, at most 10 px per stripe, unless ``--width``). Unless
the plan is the paper's own (``--measure paper --orders single``), ``--reference``, ``--plot`` and
``--validate`` make the same sweep with the paper's measure and single scattering beside it (the JSON's
``reference``; one more sweep); Fig. 10's question, rotate, translate or both, is answered for each model
made (``scans``). ``--plot`` draws the paper's Figs. 9a and 10d with both
(:mod:`polarstripe.planning.plan_plot`; the JSON's ``figure`` is what is drawn); ``--validate`` judges both
models' picks end to end, full scans through the compositor's pipeline on a grid of separations and at each
pick (:mod:`polarstripe.planning.validate_table`, docs/planning.md §7; the JSON's ``validation``), drawn on
the plot's right-hand axis. ``--light linear|circular`` plans the rig with that light (quarter-wave plates,
docs/physics.md §5.1); ``--light both`` also plans the polarized modalities with each and recommends one
(:mod:`polarstripe.planning.light`; the JSON's ``light``).
:func:`plan_to_json` and :data:`PLAN_SCHEMA` (JSON Schema 2020-12) define the JSON.
"""

from __future__ import annotations

import argparse
import json

from polarstripe.planning.light import compare_lights
from polarstripe.planning.plan_plot import (
    REFERENCE,
    check_plot_path,
    draw_figure,
    figure_data,
    print_scan_rows,
    scan_rows,
)
from polarstripe.planning.planner import (
    DEFAULT_SEARCH,
    EDGES,
    MODALITIES,
    SCAN_TYPES,
    SEARCHES,
    Curve,
    default_separations,
    plan,
    plan_model,
    resolve_search,
)
from polarstripe.planning.sheets import feasible, restrict, sheet_limits, sheets_for_budget
from polarstripe.planning.validate import EXPOSURES, ScanSettings
from polarstripe.planning.validate_table import VARIANTS, default_grid, picks_of, validate
from polarstripe.sim.scene import LIGHTS, load_scene, with_light

HELP = ("find the best camera-source separation and stripe scan (default: the least expected error of "
        "the composite against the unscattered object; --measure paper: flood CQM*W, stripes margin*W; "
        "docs/planning.md)")

MEASURES = {"flood": "CQM*W", "margin": "margin*W", "eq9": "GQM*W", "error": "1-error"}


def _curve_json(c: Curve) -> dict:
    out = {
        "separations": c.separations_m.tolist(),
        "objective": c.objective.tolist(),
        "objective_noise_free": c.objective_noise_free.tolist(),
        "quality": c.quality.tolist(),
        "weight": c.weight.tolist(),
        "saturated": c.saturated.tolist(),
        "best_separation": c.best_separation_m,
    }
    if c.limited_by is not None:
        out["limited_by"] = list(c.limited_by)
    return out


def plan_to_json(plans: dict) -> dict:
    """The plan as plain JSON types (validates against :data:`PLAN_SCHEMA`). Separations in metres."""
    out = {}
    for key, mp in plans.items():
        measure = MEASURES["error" if mp.measure == "error" else
                           "flood" if mp.modality == "flood" else mp.edge or "eq9"]
        entry = {"modality": mp.modality, "polarized": mp.polarized, "reading": mp.reading,
                 "measure": measure, "exposure_scale": mp.exposure_scale, **_curve_json(mp.curve)}
        if mp.readings:
            entry["readings"] = {r: _curve_json(c) for r, c in mp.readings.items()}
            entry["recommendation"] = dict(mp.recommendation)
        if mp.modality == "stripes":
            entry["edge"] = mp.edge
            entry["locations"] = [{**loc, **_curve_json(c)}
                                  for loc, c in zip(mp.locations, mp.location_curves, strict=True)]
            entry["scan"] = mp.scan
        out[key] = entry
    return out


_NUMS = {"type": "array", "items": {"type": "number"}, "minItems": 2}
_CURVE = {
    "separations": _NUMS, "objective": _NUMS, "objective_noise_free": _NUMS, "quality": _NUMS,
    "weight": _NUMS,
    "saturated": {"type": "array", "items": {"type": "boolean"}}, "best_separation": {"type": "number"},
    "limited_by": {"type": "array", "items": {"enum": ["neighbour", "sheet", ""]}},
}
_CURVE_OBJ = {"type": "object", "required": ["separations", "objective", "objective_noise_free",
                                             "best_separation"], "properties": _CURVE}
_ENTRY = {
    "type": "object",
    "required": ["modality", "polarized", "reading", "separations", "objective", "objective_noise_free",
                 "best_separation"],
    "properties": {"modality": {"enum": list(MODALITIES)}, "polarized": {"type": "boolean"},
                   "reading": {"enum": ["E", "E_b", "S_hat"]},
                   "measure": {"enum": sorted(set(MEASURES.values()))},
                   "exposure_scale": {"type": "number", "exclusiveMinimum": 0},
                   "readings": {"type": "object", "additionalProperties": _CURVE_OBJ},
                   "recommendation": {"type": "object", "required": ["reading", "reason"],
                                      "properties": {"reading": {"enum": ["E_b", "S_hat"]},
                                                     "reason": {"type": "string"}}},
                   **_CURVE},
}
_FLOOD_POL_ENTRY = {**_ENTRY, "required": _ENTRY["required"] + ["readings", "recommendation"]}
_STRIPE_ENTRY = {
    **_ENTRY,
    "required": _ENTRY["required"] + ["edge", "locations", "scan"],
    "properties": {
        **_ENTRY["properties"],
        "edge": {"enum": list(EDGES)},
        "locations": {"type": "array", "minItems": 1, "items": {
            "type": "object", "required": ["pixel", "lateral_position_m", "separations", "objective",
                                           "objective_noise_free", "best_separation"],
            "properties": {"pixel": {"type": "array", "items": {"type": "integer"}, "minItems": 2,
                                     "maxItems": 2},
                           "lateral_position_m": {"type": "number"}, **_CURVE}}},
        "scan": {"type": "object", "required": ["winner", "scores", "separations_m"],
                 "properties": {"winner": {"enum": list(SCAN_TYPES)},
                                "scores": {"type": "object", "required": list(SCAN_TYPES),
                                           "additionalProperties": {"type": ["number", "null"]}},
                                "separations_m": {"type": "object", "required": list(SCAN_TYPES)}}},
    },
}
_PLANS = {"flood": _ENTRY, "flood_polarized": _FLOOD_POL_ENTRY, "stripes": _STRIPE_ENTRY,
          "stripes_polarized": _STRIPE_ENTRY}
_MODEL = {"measure": {"enum": ["error", "paper"]}, "orders": {"enum": ["all", "single"]},
          "width": {"type": "integer", "minimum": 8}}
PLAN_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "polarstripe plan",
    "type": "object",
    "minProperties": 1,
    "additionalProperties": False,
    "properties": {**_PLANS,
                   "model": {"type": "object", "required": ["measure", "orders"], "properties": _MODEL},
                   "reference": {"type": "object", "required": ["measure", "orders", "plans"],
                                 "properties": {**_MODEL, "plans": {"type": "object", "minProperties": 1,
                                                                    "additionalProperties": False,
                                                                    "properties": _PLANS}}},
                   "scans": {"type": "array", "items": {
                       "type": "object", "required": ["plan", "model", "label", "winner", "scores"],
                       "properties": {"plan": {"enum": ["stripes", "stripes_polarized"]},
                                      "model": {"enum": ["plan", "reference"]},
                                      "winner": {"enum": list(SCAN_TYPES)}}}},
                   "search": {"type": "object",
                              "required": ["separations", "refine", "rivals", "evaluations"],
                              "properties": {"evaluations": {"type": "object", "additionalProperties": {
                                  "type": "integer", "minimum": 2}}}},
                   "figure": {"type": "object", "required": ["panels"]},
                   "sheets": {"type": "object", "required": ["sheets", "max_frames", "frames", "allowed"]},
                   "light": {"type": "object", "required": ["recommended", "lights", "tie"], "properties": {
                       "recommended": {"type": "object", "additionalProperties": {"enum": list(LIGHTS)}}}},
                   "validation": {"type": "object", "required": ["grid_m", "rows", "curves"],
                                  "properties": {"rows": {"type": "array", "items": {
                                      "type": "object", "required": ["plan", "method", "image", "pick_m",
                                                                     "pick_error", "best_m", "regret"]}}}}},
}


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", nargs="?", default=None,
                        help="scene TOML file (default: the paper's tank)")
    parser.add_argument("--modality", choices=["flood", "stripes"], default=None,
                        help="plan one modality only (default: both)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    parser.add_argument("--plot", metavar="PNG", default=None,
                        help="draw the paper's Figs. 9a and 10d anew into this PNG (or .pdf, .svg) file: "
                        "the plan's curves beside the paper's measure with single scattering, and with "
                        "--validate the end-to-end errors (docs/planning.md §9)")
    parser.add_argument("--measure", choices=("error", "paper"), default="error",
                        help="what is maximised: 'error' (default: 1 − the composite's expected error "
                             "against the unscattered object, from low-resolution whole frames) or 'paper' "
                             "(CQM·W, the delineation margin or eq. 9 ·W at three observed points)")
    parser.add_argument("--fidelity", default=None,
                        help="model fidelity: draft (the error measure's cheapest), preview, standard, "
                             "reference (default: preview for the error "
                             "measure, standard for the paper's)")
    parser.add_argument("--search", choices=list(SEARCHES), default=DEFAULT_SEARCH,
                        help="which separations are evaluated (docs/planning.md §8, 'The search'): coarse "
                        "(default: {c.separations} even, then {c.refine} rounds of bisection around each "
                        "curve's best and its rivals), exhaustive ({e.separations} even, {e.refine} rounds "
                        "around the best alone)".format(c=SEARCHES["coarse"], e=SEARCHES["exhaustive"]))
    parser.add_argument("--separations", type=int, default=None,
                        help="number of separations of the first, even grid (default: the search's)")
    parser.add_argument("--range", nargs=2, type=float, default=(0.01, 0.6), metavar=("MIN_M", "MAX_M"),
                        help="separation range in metres (default 0.01 0.6)")
    parser.add_argument("--refine", type=int, default=None, metavar="N",
                        help="rounds of bisection around each curve's peaks, down to the grid's step / 2^N "
                             "(default: the search's; 0: the grid alone); the stripe composite's error "
                             "ripples between the grid's points")
    parser.add_argument("--rivals", type=float, default=None, metavar="TOL",
                        help="also bisect around local maxima whose expected error is within TOL "
                             "(relative) of the best's (default: the search's; 0: the best alone)")
    parser.add_argument("--stripes", type=int, default=30, help="stripes per scan (default 30)")
    parser.add_argument("--width", type=int, default=None, metavar="W",
                        help="width [px] of the error measure's renders (default: the scene camera's, whose "
                        "pixel grid a stripe composite aliases on, at most 10 px per stripe; at least 3 px "
                        "per stripe; a smaller one costs less, docs/planning.md §8)")
    parser.add_argument("--max-frames", type=int, default=0, metavar="N",
                        help="frame budget of a polarized stripe scan (two analyzer passes; --analyzer "
                        "mosaic: one): plan the fewest sheets per frame that fit, with their backscatter, at "
                        "separations where they stay apart in the image (error measure; planning.md §12)")
    parser.add_argument("--analyzer", choices=("stage", "mosaic"), default="stage",
                        help="what --max-frames counts: a rotating analyzer's two passes (default) or a "
                        "polarization camera's one")
    parser.add_argument("--exposure", choices=["scene", "auto"], default="scene",
                        help="scene: the camera's exposure_s, saturated points score 0 (default); auto: one "
                        "exposure per modality, the longest with no saturation over the sweep")
    parser.add_argument("--edge", choices=list(EDGES), default="margin",
                        help="stripe measure: margin (default), O's own-sheet intensity against the "
                        "brightest competitor (O under the other sheets, the unlit neighbour O'); eq9, the "
                        "paper's eq. 9 as printed, which counts the sheet's own backscatter as edge signal "
                        "and so favours the co-located source (docs/planning.md)")
    parser.add_argument("--orders", choices=("all", "single"), default="all",
                        help="orders of scattering of the planner's model: all (default: those the scene "
                        "needs, sim/orders.py, as the simulator renders) or the paper's single scattering")
    parser.add_argument("--p-rule", choices=("map", "median"), default="map",
                        help="eq. 6's p the error measure predicts the polarized composites with, and "
                        "--validate composes them with: map (default, the compositor's: per pixel from the "
                        "medium's model) or median (one p-hat)")
    parser.add_argument("--reference", action="store_true",
                        help="also plan with the paper's measure and single scattering, beside the plan "
                        "(always with --plot and --validate; one more sweep)")
    parser.add_argument("--validate", action="store_true",
                        help="judge the picks end to end: full scans (all orders, standard) through the "
                        "compositor's pipeline, error vs the unscattered object, regret (planning.md §7)")
    parser.add_argument("--validate-grid", type=int, default=8, metavar="N",
                        help="separations of --validate's grid, log-spaced 2-60 cm (default 8)")
    parser.add_argument("--validate-width", type=int, default=None, metavar="W",
                        help="camera width of --validate's scans (default: the plan's render width, so the "
                        "judge's stripes fall on the pixels the plan predicted)")
    parser.add_argument("--validate-exposure", choices=EXPOSURES, default="rig",
                        help="exposure of --validate's scans (default rig: see bench planner --help)")
    parser.add_argument("--light", choices=("scene", *LIGHTS, "both"), default="scene",
                        help="the polarization optics: the scene's (default), linear or circular light "
                             "(quarter-wave plates on source and analyzer), or both: plan the polarized "
                             "modalities with each and recommend one (docs/physics.md §5.1)")
    parser.add_argument("--k-detect", type=float, default=3.0,
                        help="detection threshold in noise std for the SNR weight W (default 3)")


def _limits(loc: dict) -> str:
    """'sheets below 7 cm, neighbour above' from a location's limited_by list."""
    lim, seps = loc.get("limited_by"), loc["separations"]
    if not lim:
        return ""
    runs, start = [], 0
    for k in range(1, len(lim) + 1):
        if k == len(lim) or lim[k] != lim[start]:
            runs.append(f"{lim[start] or 'none'} {seps[start] * 100:.0f}-{seps[k - 1] * 100:.0f} cm")
            start = k
    return "; limited by " + ", ".join(runs)


def _print_tables(doc: dict) -> None:
    for modality in ("flood", "stripes"):
        if modality not in doc:
            continue
        plain, pol = doc[modality], doc[modality + "_polarized"]
        measure = plain["measure"]
        print(f"{modality}: {measure}, exposure ×{plain['exposure_scale']:.3g} of the scene's")
        print(f"  best d_LC = {plain['best_separation'] * 100:.1f} cm without a polarizer "
              f"({measure} = {max(plain['objective']):.4g}), {pol['best_separation'] * 100:.1f} cm with one "
              f"({pol['reading']}, {measure} = {max(pol['objective']):.4g})")
        cols = [("E", plain)]
        if "readings" in pol:
            rec = pol["recommendation"]
            print(f"  polarized reading: {rec['reading']} — {rec['reason']}")
            cols += [(r, {**c, "saturated": c.get("saturated", [])}) for r, c in pol["readings"].items()]
        else:
            cols.append((pol["reading"], pol))
        if modality == "stripes":
            for tag, entry in (("unpolarized", plain), ("polarized", pol)):
                scan = entry["scan"]
                scores = ", ".join(f"{k} {v:.4g}" if v is not None else f"{k} n/a"
                                   for k, v in scan["scores"].items())
                print(f"  {tag}: scan scores {scores}; winner: {scan['winner']}")
                for i, loc in enumerate(entry["locations"]):
                    print(f"    O{i + 1} best {loc['best_separation'] * 100:.1f} cm{_limits(loc)}")
        head = "".join(f" {r:>7} {r + ' n-f':>9} {'W ' + r:>7}" for r, _ in cols)
        print(f"  {'d_LC [cm]':>9}{head}")
        for k, d in enumerate(plain["separations"]):
            row = "".join(f" {c['objective'][k]:7.4f} {c['objective_noise_free'][k]:9.4f} "
                          f"{c['weight'][k]:7.3f}" for _, c in cols)
            sat = " saturated" if any(c["saturated"][k] for _, c in cols if c.get("saturated")) else ""
            print(f"  {d * 100:9.1f}{row}{sat}")


def _print_light(light: dict) -> None:
    for key, pick in light["recommended"].items():
        parts = ", ".join(f"{lt} {e[key]['expected_error']:.3f} at {e[key]['separation_m'] * 100:.1f} cm "
                          f"(p {e[key]['p']:.2f})" for lt, e in light["lights"].items())
        print(f"light for {key}: {pick} (expected error {parts})")


def _print_validation(v: dict) -> None:
    g = v["grid_m"]
    print(f"end to end ({len(g)} separations {g[0] * 100:.0f}-{g[-1] * 100:.0f} cm and each pick; error vs "
          "the unscattered object, whole frame, gain fitted; regret = error at the pick / best):")
    print(f"  {'plan':<7} {'method':<18} {'image':<9} {'pick cm':>8} {'error':>6} {'best cm':>8} "
          f"{'error':>6} {'regret':>7}")

    def num(x, f):
        return "-" if x is None else format(x, f)

    for r in v["rows"]:
        print(f"  {r['plan']:<7} {r['method']:<18} {r['image']:<9} {r['pick_m'] * 100:8.1f} "
              f"{num(r['pick_error'], '6.3f')} "
              f"{num(r['best_m'] and r['best_m'] * 100, '7.1f')}{'>' if r['best_at_edge'] else ' '} "
              f"{num(r['best_error'], '6.3f')} {num(r['regret'], '7.3f')}")


def _variant(measure: str, orders: str) -> str:
    """The name of a planner variant in the validation's rows (validate_table.VARIANTS)."""
    return next((k for k, v in VARIANTS.items() if v == (measure, orders)), f"{measure}-{orders}")


def main(args: argparse.Namespace) -> int:
    if args.plot:
        check_plot_path(args.plot)
    scene = load_scene(args.scene)
    if args.light in LIGHTS:
        scene = with_light(scene, args.light)
    search = resolve_search(args.search, separations=args.separations, refine=args.refine, rivals=args.rivals)
    seps = default_separations(search.separations, args.range[0], args.range[1])
    modalities = (args.modality,) if args.modality else ("flood", "stripes")
    plans, doc = {}, {}
    sheets, allowed, sheet_seps = 1, None, seps
    if args.max_frames:
        sheets = sheets_for_budget(args.stripes, args.max_frames, 2 if args.analyzer == "stage" else 1)
    for role, measure, orders in (("plan", args.measure, args.orders),
                                  ("reference", REFERENCE["measure"], REFERENCE["orders"])):
        if role == "reference" and ((args.measure, args.orders) == (measure, orders) or
                                    not (args.reference or args.plot or args.validate)):
            break  # the plan is the paper's own, or nothing asks for the comparison (it costs a sweep)
        model = plan_model(scene, measure=measure, fidelity=args.fidelity, n_stripes=args.stripes,
                           edge=args.edge, orders=orders, sheets=sheets if role == "plan" else 1,
                           p_rule=args.p_rule, width=args.width)
        if role == "plan":
            plan_width = model.shape[1] if measure == "error" else args.width or scene.camera.resolution[0]
        plans[role] = plan(model, seps, modalities=modalities, k_detect=args.k_detect, exposure=args.exposure,
                           refine=search.refine, rivals=search.rivals)
        if role == "plan" and args.max_frames:     # at the stripe curves' own separations (bisections too)
            sheet_seps = plans[role]["stripes"].curve.separations_m if "stripes" in plans[role] else seps
            allowed = feasible(sheet_limits(scene, args.stripes, sheet_seps), sheets)
            restrict(plans[role], allowed)
        if role == "plan":
            doc = {**plan_to_json(plans[role]), "model": {"measure": measure, "orders": orders},
                   "search": {"name": args.search, "separations": search.separations, "refine": search.refine,
                              "rivals": search.rivals,
                              "evaluations": {m: plans[role][m].evaluations for m in modalities}}}
            if measure == "error":
                doc["model"]["width"] = plan_width     # the renders' width [px]
        else:
            doc["reference"] = {"measure": measure, "orders": orders, "plans": plan_to_json(plans[role])}
    doc["scans"] = scan_rows(doc)
    if args.max_frames:
        doc["sheets"] = {"sheets": sheets, "max_frames": args.max_frames, "analyzer": args.analyzer,
                         "frames": -(-args.stripes // sheets) * (2 if args.analyzer == "stage" else 1),
                         "allowed": [bool(a) for a in allowed]}
    if args.light == "both":
        doc["light"] = compare_lights(scene, seps, modalities=modalities, fidelity=args.fidelity,
                                      n_stripes=args.stripes, orders=args.orders, width=args.width,
                                      refine=search.refine, rivals=search.rivals)
    if args.validate:
        settings = ScanSettings(n_stripes=args.stripes, width=args.validate_width or plan_width,
                                exposure=args.validate_exposure, p_rule=args.p_rule)
        picks = {_variant(args.measure, args.orders): picks_of(plans["plan"])}
        if "reference" in plans:
            picks[_variant(REFERENCE["measure"], REFERENCE["orders"])] = picks_of(plans["reference"])
        res = validate(scene, default_grid(args.validate_grid), settings, picks=picks)
        doc["validation"] = {"grid_m": res["grid_m"], "settings": vars(settings), "rows": res["rows"],
                             "curves": res["curves"], "extra": res["extra"]}
    if args.plot:
        doc["figure"] = figure_data(doc)
        draw_figure(doc["figure"], args.plot)
    if args.json:
        print(json.dumps(doc))
    else:
        if "sheets" in doc:
            s = doc["sheets"]
            ok = [d for d, a in zip(sheet_seps, s["allowed"], strict=True) if a]
            print(f"sheets: {s['sheets']} per stripe frame ({s['frames']} frames of a polarized scan, budget "
                  f"{s['max_frames']}); they stay apart in the image at "
                  + (f"{ok[0] * 100:.0f}-{ok[-1] * 100:.0f} cm" if ok else "no separation"))
        m = doc["model"]
        print(f"model: {m['measure']} measure, {m['orders']} orders"
              + (f", renders {m['width']} px wide" if "width" in m else ""))
        sr = doc["search"]
        print(f"search: {sr['name']}, {sr['separations']} separations, {sr['refine']} bisection round(s), "
              f"rivals within {sr['rivals']:g}; model evaluations "
              + ", ".join(f"{m} {n}" for m, n in sr["evaluations"].items()))
        _print_tables(doc)
        print_scan_rows(doc["scans"])
        if "light" in doc:
            _print_light(doc["light"])
        if "validation" in doc:
            _print_validation(doc["validation"])
        if args.plot:
            print(f"plot written to {args.plot}")
    return 0
